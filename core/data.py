"""Dataset utilities shared by every stage: deterministic splits and subsets, the user cache folder."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from .components import TactileDataset
from .errors import ConfigError


class DatasetSubset(TactileDataset):
    """Some samples of a dataset, in a fixed order; keeps the class names."""

    def __init__(self, dataset: TactileDataset, indices: list[int]) -> None:
        self.dataset = dataset
        self.indices = indices
        self.class_names = list(getattr(dataset, "class_names", []))

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, index: int) -> dict[str, Any]:
        return self.dataset[self.indices[index]]


def split_dataset(dataset: TactileDataset, val_fraction: float, seed: int) -> tuple[DatasetSubset, DatasetSubset]:
    """A held-out split that depends only on (len(dataset), val_fraction, seed)."""
    size = len(dataset)
    val_count = int(round(size * val_fraction))
    if val_fraction > 0 and val_count == 0:
        val_count = 1
    if size - val_count < 1:
        raise ConfigError(f"the dataset has {size} samples: too few to hold out {val_fraction:.0%} for evaluation")
    order = torch.randperm(size, generator=torch.Generator().manual_seed(seed + 7777)).tolist()
    return DatasetSubset(dataset, sorted(order[val_count:])), DatasetSubset(dataset, sorted(order[:val_count]))


def user_cache_folder() -> Path | None:
    """vqtouch's user cache folder: $XDG_CACHE_HOME/vqtouch, else ~/.cache/vqtouch; None without a home.

    Only speed-ups live there (image headers already checked, tokenizer codes already computed):
    deleting it is always safe.
    """
    xdg = os.environ.get("XDG_CACHE_HOME", "")
    if os.path.isabs(xdg):  # the XDG specification says to ignore relative paths
        return Path(xdg) / "vqtouch"
    try:
        return Path.home() / ".cache" / "vqtouch"
    except (RuntimeError, KeyError):
        return None

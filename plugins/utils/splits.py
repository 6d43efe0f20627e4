"""Dataset utilities shared by every stage: deterministic splits and subsets, the user cache folder."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from vqtouch.core.components import TactileDataset
from vqtouch.core.errors import ConfigError, PluginError

# The split's generator is seeded apart from the experiment's seed, so that its draws are not the ones every
# other generator seeded with that seed starts with.
_SPLIT_SEED_OFFSET = 7777
# The training-subset draw's own offset, for the same reason (and so it is not the split's order).
_SUBSET_SEED_OFFSET = 9191


class DatasetSubset(TactileDataset):
    """Some samples of a dataset, in a fixed order; keeps the class names and the split groups."""

    def __init__(self, dataset: TactileDataset, indices: list[int]) -> None:
        self.dataset = dataset
        self.indices = indices
        self.class_names = list(getattr(dataset, "class_names", []))
        self.split_unit = getattr(dataset, "split_unit", TactileDataset.split_unit)

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, index: int) -> dict[str, Any]:
        return self.dataset[self.indices[index]]

    def split_groups(self) -> list[str] | None:
        """The parent dataset's groups of the samples of this subset, in its order (None without groups)."""
        groups = dataset_groups(self.dataset)
        return None if groups is None else [groups[index] for index in self.indices]

    def rendering_sensor(self) -> Any | None:
        """The parent dataset's rendering sensor (None for captured frames or a dataset without the method)."""
        rendering_sensor = getattr(self.dataset, "rendering_sensor", None)
        return rendering_sensor() if rendering_sensor is not None else None


def dataset_groups(dataset: TactileDataset) -> list[str] | None:
    """``dataset.split_groups()``, checked to hold one key per sample; None for a dataset without groups."""
    split_groups = getattr(dataset, "split_groups", None)
    groups = split_groups() if split_groups is not None else None
    if groups is not None and len(groups) != len(dataset):
        raise PluginError(
            f"{type(dataset).__name__}.split_groups() returned {len(groups)} keys for {len(dataset)} "
            f"samples; it must return one key per sample, in index order"
        )
    return groups


def split_dataset(dataset: TactileDataset, val_fraction: float, seed: int) -> tuple[DatasetSubset, DatasetSubset]:
    """A (train, held-out) split for evaluation, deterministic in its inputs.

    A dataset with split groups (:meth:`TactileDataset.split_groups`: the frames of one recording,
    ...) is split by whole groups, so that no near-duplicate of a held-out image is trained on: the
    held-out groups depend only on (the groups, ``val_fraction``, ``seed``), at least one group is
    held out when ``val_fraction > 0`` and the held-out share is as close to ``val_fraction`` as
    whole groups allow.  Otherwise samples are held out one by one, depending only on
    (len(dataset), ``val_fraction``, ``seed``).  Both subsets' ``split_unit`` names the unit that
    was held out ("sample", "recording", ...).
    """
    groups = dataset_groups(dataset)
    if groups is None:
        train_indices, held_out_indices = _split_samples(len(dataset), val_fraction, seed)
        unit = TactileDataset.split_unit
    else:
        unit = getattr(dataset, "split_unit", TactileDataset.split_unit)
        train_indices, held_out_indices = _split_groups(groups, val_fraction, seed, unit)
    train, held_out = DatasetSubset(dataset, train_indices), DatasetSubset(dataset, held_out_indices)
    train.split_unit = held_out.split_unit = unit
    return train, held_out


def experiment_split(dataset: TactileDataset, data: Any, seed: int) -> tuple[DatasetSubset, DatasetSubset]:
    """The experiment's (train, held-out) split of ``dataset``: :func:`split_dataset` with
    ``data.val_fraction``, then, when ``data.train_samples`` is set, only that many samples of the
    training split (:func:`first_samples`).  Every stage and command that trains on or scores a
    run's data takes its split from here, so they agree on it.  The held-out split never depends on
    ``data.train_samples``: runs trained on different amounts of data are scored on the same images."""
    train, held_out = split_dataset(dataset, data.val_fraction, seed)
    count = getattr(data, "train_samples", None)
    if count is not None:
        if count > len(train):
            raise ConfigError(
                f"data.train_samples={count}, but the training split holds {len(train)} samples "
                f"({len(dataset)} in the dataset, {len(held_out)} held out); lower "
                "data.train_samples or give the dataset more samples"
            )
        train = first_samples(train, count, seed)
    return train, held_out


def first_samples(subset: DatasetSubset, count: int, seed: int) -> DatasetSubset:
    """``count`` samples of ``subset`` drawn in a seeded order, kept in dataset order.  The order
    depends only on (len(subset), ``seed``), so with one seed a smaller count is a subset of a
    larger one: the training-set-size experiment adds data without swapping what was there."""
    order = torch.randperm(len(subset), generator=torch.Generator().manual_seed(seed + _SUBSET_SEED_OFFSET)).tolist()
    chosen = DatasetSubset(subset.dataset, sorted(subset.indices[position] for position in order[:count]))
    chosen.split_unit = subset.split_unit
    return chosen


def _split_samples(size: int, val_fraction: float, seed: int) -> tuple[list[int], list[int]]:
    val_count = int(round(size * val_fraction))
    if val_fraction > 0 and val_count == 0:
        val_count = 1
    if size - val_count < 1:
        raise ConfigError(f"the dataset has {size} samples: too few to hold out {val_fraction:.0%} for evaluation")
    order = torch.randperm(size, generator=torch.Generator().manual_seed(seed + _SPLIT_SEED_OFFSET)).tolist()
    return sorted(order[val_count:]), sorted(order[:val_count])


def _split_groups(groups: list[str], val_fraction: float, seed: int, unit: str) -> tuple[list[int], list[int]]:
    members: dict[str, list[int]] = {}
    for index, key in enumerate(groups):
        members.setdefault(key, []).append(index)
    if val_fraction <= 0:
        return list(range(len(groups))), []
    if len(members) < 2:
        raise ConfigError(
            f"the dataset's {len(groups)} samples are all one {unit}: too few to hold out whole "
            f"{unit}s for evaluation; add samples of other {unit}s or set data.val_fraction=0"
        )
    # Sorted keys: the split must not depend on the order the reader listed its samples in.
    keys = sorted(members)
    order = torch.randperm(len(keys), generator=torch.Generator().manual_seed(seed + _SPLIT_SEED_OFFSET)).tolist()
    target = len(groups) * val_fraction
    # Hold out the first k groups of the shuffled order, k from 1 to all but one, with the count closest to
    # the target: a prefix of a random order, so large groups are as likely to be held out as small ones.
    held_out_count, best_count, best_groups = 0, None, 0
    for taken, position in enumerate(order[:-1], start=1):
        held_out_count += len(members[keys[position]])
        if best_count is None or abs(held_out_count - target) < abs(best_count - target):
            best_count, best_groups = held_out_count, taken
    held_out = sorted(index for position in order[:best_groups] for index in members[keys[position]])
    held_out_set = set(held_out)
    return [index for index in range(len(groups)) if index not in held_out_set], held_out


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

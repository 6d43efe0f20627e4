"""Reproducibility: one call seeds every random number generator a run uses; devices by name.

The thread policy (one-thread sections, a command's thread count) is :mod:`.threads`."""

from __future__ import annotations

import os
import random
from typing import TYPE_CHECKING

from vqtouch.core.config import SEED_MAX

if TYPE_CHECKING:
    import torch


def seed_everything(seed: int, deterministic: bool = False) -> int:
    """Seed Python, NumPy and PyTorch (all devices); optionally force deterministic kernels.

    Returns the seed so callers can record it.  ``deterministic=True`` makes PyTorch raise
    on operations without a deterministic implementation rather than silently vary.
    """
    import numpy as np
    import torch

    if not 0 <= seed <= SEED_MAX:
        raise ValueError(f"seed must be in [0, {SEED_MAX}], got {seed}")
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)
    if deterministic:
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
        torch.use_deterministic_algorithms(True)
        torch.backends.cudnn.benchmark = False
    return seed


def make_generator(seed: int, device: str | torch.device = "cpu") -> torch.Generator:
    """A fresh ``torch.Generator`` on ``device`` seeded with ``seed`` (for explicit randomness)."""
    import torch

    generator = torch.Generator(device=device)
    generator.manual_seed(seed)
    return generator


def resolve_device(device: str) -> torch.device:
    """Map a config device (``auto``, ``cpu``, ``cuda``) to a ``torch.device``, failing clearly."""
    import torch
    from vqtouch.core.errors import ConfigError

    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"device {device!r} requested but CUDA is not available; use device=cpu or auto")
    return torch.device(device)

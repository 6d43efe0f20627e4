"""Reproducibility: one call seeds every random number generator a run uses; one context makes
CPU float sums independent of the thread count."""

from __future__ import annotations

import contextlib
import functools
import os
import random
from collections.abc import Callable, Iterator
from typing import Any, TypeVar

import numpy as np
import torch

#: The largest seed: NumPy takes seeds below 2**32, and the seeds vqtouch derives from one
#: (``seed * 1_000_003 + index`` for each generated image, ...) then stay within 64 bits.
SEED_MAX = 2**32 - 1


def seed_everything(seed: int, deterministic: bool = False) -> int:
    """Seed Python, NumPy and PyTorch (all devices); optionally force deterministic kernels.

    Returns the seed so callers can record it.  ``deterministic=True`` makes PyTorch raise
    on operations without a deterministic implementation rather than silently vary.
    """
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
    generator = torch.Generator(device=device)
    generator.manual_seed(seed)
    return generator


def resolve_device(device: str) -> torch.device:
    """Map a config device (``auto``, ``cpu``, ``cuda``) to a ``torch.device``, failing clearly."""
    from .errors import ConfigError

    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"device {device!r} requested but CUDA is not available; use device=cpu or auto")
    return torch.device(device)


_F = TypeVar("_F", bound=Callable[..., Any])


@contextlib.contextmanager
def one_thread() -> Iterator[None]:
    """Run torch's CPU kernels and the BLAS/OpenMP pools (scikit-learn, NumPy) on one thread inside.

    A parallel reduction adds its partial sums in an order that depends on the thread count, so the
    same features differ by about 1e-8 between 1 and 2 threads; a decision taken on them (a family
    count chosen by silhouette, a k-means partition, a nearest family) can then flip with the
    machine's load or ``OMP_NUM_THREADS``.  One thread fixes the order on every machine.  The
    previous thread counts are restored on exit."""
    from threadpoolctl import threadpool_limits

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with threadpool_limits(limits=1):
            yield
    finally:
        torch.set_num_threads(before)


def on_one_thread(function: _F) -> _F:
    """Decorate ``function`` to run inside :func:`one_thread`."""

    @functools.wraps(function)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        with one_thread():
            return function(*args, **kwargs)

    return wrapper  # type: ignore[return-value]

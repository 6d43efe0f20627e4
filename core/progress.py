"""Progress bars: tqdm, off when output is not a terminal or when the user asks.

Set ``VQTOUCH_NO_PROGRESS=1`` (or pass ``--no-progress`` to the CLI) to disable bars.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from typing import Any, TypeVar

from tqdm.auto import tqdm

T = TypeVar("T")
ENV_NO_PROGRESS = "VQTOUCH_NO_PROGRESS"

_forced_off = False


def disable_progress(disabled: bool = True) -> None:
    """Turn progress bars off (or back on) for the rest of the process."""
    global _forced_off
    _forced_off = disabled


def progress_enabled() -> bool | None:
    """``False`` when bars are turned off; ``None`` lets tqdm decide (off on non-TTY output)."""
    if _forced_off or os.environ.get(ENV_NO_PROGRESS, "").strip() not in {"", "0"}:
        return False
    return None


def progress(
    iterable: Iterable[T] | None = None, *, total: int | None = None, desc: str = "", unit: str = "it", **kwargs: Any
) -> Any:
    """A tqdm bar over ``iterable`` that respects the global and environment switches."""
    enabled = progress_enabled()
    return tqdm(
        iterable,
        total=total,
        desc=desc,
        unit=unit,
        dynamic_ncols=True,
        disable=True if enabled is False else None,
        **kwargs,
    )

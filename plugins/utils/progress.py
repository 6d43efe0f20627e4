"""Progress bars: tqdm on a terminal; one plain line at least every 30 s when output is redirected
(a log file or a pipe: a long stage still shows it is alive, without a redrawn bar's noise); off
when the user asks.

Set ``VQTOUCH_NO_PROGRESS=1`` (or pass ``--no-progress`` to the CLI) to disable bars.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterable
from typing import IO, Any, TypeVar

from tqdm.auto import tqdm

T = TypeVar("T")
ENV_NO_PROGRESS = "VQTOUCH_NO_PROGRESS"

_forced_off = False


def disable_progress(disabled: bool = True) -> None:
    """Turn progress bars off (or back on) for the rest of the process."""
    global _forced_off
    _forced_off = disabled


def progress_forced_off() -> bool:
    """Whether :func:`disable_progress` turned bars off in this process."""
    return _forced_off


def progress_enabled() -> bool | None:
    """``False`` when bars are turned off; ``None`` otherwise (:func:`progress` then picks a bar or
    plain lines by its stream)."""
    if _forced_off or os.environ.get(ENV_NO_PROGRESS, "").strip() not in {"", "0"}:
        return False
    return None


#: With output redirected, a bar prints its first line after this many seconds and then at most
#: one line per this many seconds (at its updates); shorter bars print nothing.
REDIRECTED_INTERVAL_S = 30.0


class _LineWriter:
    """What tqdm writes, as whole lines: tqdm redraws a bar with a carriage return, which in a log
    file piles every state onto one line; each refresh becomes a line of its own instead."""

    def __init__(self, stream: IO[str]) -> None:
        self.stream = stream
        self._pending = ""

    def write(self, text: str) -> None:
        state = text.replace("\r", "").strip()
        if state:
            self._pending = state

    def flush(self) -> None:
        if self._pending:
            self.stream.write(self._pending + "\n")
            self.stream.flush()
            self._pending = ""


def progress(
    iterable: Iterable[T] | None = None,
    *,
    total: int | None = None,
    desc: str = "",
    unit: str = "it",
    stream: IO[str] | None = None,
    **kwargs: Any,
) -> Any:
    """A tqdm bar over ``iterable`` on ``stream`` (standard error) that respects the global and
    environment switches: a redrawn bar on a terminal, a line every :data:`REDIRECTED_INTERVAL_S`
    when the stream is not one."""
    stream = stream if stream is not None else sys.stderr
    if progress_enabled() is False:
        return tqdm(iterable, total=total, desc=desc, unit=unit, disable=True, **kwargs)
    if not getattr(stream, "isatty", lambda: False)():
        options = {"mininterval": REDIRECTED_INTERVAL_S, "delay": REDIRECTED_INTERVAL_S, "ascii": True, "ncols": 100}
        # The redirected pacing wins over a caller's terminal-minded delay or interval.
        return tqdm(iterable, total=total, desc=desc, unit=unit, file=_LineWriter(stream), **(kwargs | options))
    return tqdm(iterable, total=total, desc=desc, unit=unit, dynamic_ncols=True, file=stream, **kwargs)

"""Thread policy: how many CPU threads a command's torch kernels use, and one-thread sections whose
float sums do not depend on the thread count."""

from __future__ import annotations

import contextlib
import functools
import os
import sys
from collections.abc import Callable, Iterator
from typing import Any, TypeVar

from vqtouch.core.errors import ConfigError

_F = TypeVar("_F", bound=Callable[..., Any])


@contextlib.contextmanager
def one_thread() -> Iterator[None]:
    """Run torch's CPU kernels and the BLAS/OpenMP pools (scikit-learn, NumPy) on one thread inside.

    A parallel reduction adds its partial sums in an order that depends on the thread count, so the
    same features differ by about 1e-8 between 1 and 2 threads; a decision taken on them (a family
    count chosen by silhouette, a k-means partition, a nearest family) can then flip with the
    machine's load or ``OMP_NUM_THREADS``.  One thread fixes the order on every machine.  The
    previous thread counts are restored on exit."""
    import torch
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


#: ``VQTOUCH_THREADS``: torch's CPU threads for a command (as ``--threads``): a number, ``auto`` (the
#: default: fewer when the CPU is busy) or ``0`` (torch's own default, whatever the load).
ENV_THREADS = "VQTOUCH_THREADS"


#: More threads than this per core only make torch's threads wait for each other.
THREADS_PER_CORE = 8


def max_threads() -> int:
    """The most CPU threads a command accepts on this machine (``--threads``, ``VQTOUCH_THREADS``)."""
    return THREADS_PER_CORE * available_cores()


def available_cores() -> int:
    """The CPU cores this process may run on (its affinity, else the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        return os.cpu_count() or 1


def busy_cpu_threads(cores: int, load: float, wanted: int) -> tuple[int, str | None]:
    """The threads to run on given the load (:func:`current_load`), and a note when it is not ``wanted``
    (torch's default): with the load above the cores, every extra OpenMP thread spins on a shared
    core and slows every process on it (a 2-minute demo took 39 minutes beside five other jobs),
    so the cores left free (rounded), at least one."""
    threads = max(1, min(wanted, int(cores - load + 0.5)))
    if threads >= wanted:
        return wanted, None
    return threads, (
        f"the CPU is busy (load {load:.1f} on {cores} cores): running on {threads} thread{'s' if threads > 1 else ''} "
        f"instead of {wanted}; --threads N (or {ENV_THREADS}=N) to choose"
    )


def current_load(samples: int = 5, interval_s: float = 0.02) -> float:
    """How many other tasks want a CPU now: the median over a few samples of the runnable tasks
    Linux counts in /proc/loadavg, less this one.  The 1-minute load average lags a minute behind
    (right after ``make test`` it still says busy); it is the fallback elsewhere."""
    import statistics
    import time

    counts = []
    try:
        for index in range(samples):
            if index:
                time.sleep(interval_s)
            with open("/proc/loadavg", encoding="ascii") as handle:
                counts.append(int(handle.read().split()[3].split("/")[0]) - 1)
    except (OSError, ValueError, IndexError):
        try:
            return os.getloadavg()[0]
        except (AttributeError, OSError):  # no load average here (Windows)
            return 0.0
    return float(statistics.median(counts))


@contextlib.contextmanager
def command_threads(requested: str | int | None) -> Iterator[str | None]:
    """Torch's CPU threads while a command runs, restored afterwards; yields the note to print when
    the load chose fewer.  ``requested``: ``--threads`` (a number), else ``VQTOUCH_THREADS``, else
    ``auto`` (:func:`busy_cpu_threads`); ``0``: leave torch's default.  A command that has not
    imported torch (help, configs, listings: the CLI imports a command's implementation first)
    only has the value checked: it runs no torch kernel, and loading torch for it would cost a
    second of start-up."""
    value = requested if requested is not None else os.environ.get(ENV_THREADS, "auto").strip() or "auto"
    given = f"--threads {value}" if requested is not None else f"{ENV_THREADS}={value!r}"
    threads = None if str(value) == "auto" else _checked_threads(value, given)
    torch = sys.modules.get("torch")
    if torch is None:
        yield None
        return
    before = torch.get_num_threads()
    note = None
    if threads is None:
        threads, note = busy_cpu_threads(available_cores(), current_load(), before)
    torch.set_num_threads(threads or before)
    try:
        yield note
    finally:
        torch.set_num_threads(before)


def _checked_threads(value: str | int, given: str) -> int:
    """A thread count given as ``--threads``/``VQTOUCH_THREADS``, or a one-line ConfigError."""
    try:
        threads = int(value)
    except ValueError:
        raise ConfigError(f"{given}: give a number of threads, 0 (torch's default) or auto") from None
    if threads < 0:
        raise ConfigError(f"{given}: give a number of threads >= 0")
    most = max_threads()
    if threads > most:  # torch's thread pool crashes (SIGSEGV) long before a huge count is reached
        raise ConfigError(
            f"{given}: at most {most} threads here ({THREADS_PER_CORE} per core of {available_cores()}); "
            "give fewer, or 0 for torch's default"
        )
    return threads

"""The processes of a training run: stop signals that finish the current step first, and the
data-parallel context under ``torchrun``."""

from __future__ import annotations

import atexit
import contextlib
import datetime
import os
import signal
import threading
from dataclasses import dataclass
from typing import Any

import torch


def notice(message: str) -> None:
    # From a signal handler: a raw write, since the handler may run in the middle of another
    # write to sys.stderr (the progress bar) and buffered streams are not reentrant.
    try:
        os.write(2, f"\n{message}\n".encode())
    except OSError:
        pass


class StopSignals:
    """SIGINT and SIGTERM as requests to stop at the end of the current step.

    Installed by :meth:`Trainer.fit` (which checks :attr:`received` after every step and
    restores the previous handlers when it returns) and, outside fit, around each checkpoint
    save (which then re-raises the signal to the previous handler once the save is complete).
    Nothing is installed outside the main thread (Python allows handlers only there) nor for a
    signal that is ignored on purpose (nohup).
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.received: int | None = None
        self.saving = False
        self._previous: dict[int, Any] = {}
        self._pid = os.getpid()

    def install(self) -> StopSignals:
        if threading.current_thread() is threading.main_thread():
            for signum in self.SIGNALS:
                previous = signal.getsignal(signum)
                if previous is signal.SIG_IGN or previous is None:
                    continue
                self._previous[signum] = previous
                signal.signal(signum, self._handle)
        return self

    def restore(self) -> None:
        for signum, previous in self._previous.items():
            signal.signal(signum, previous)
        self._previous.clear()

    def _handle(self, signum: int, frame: Any) -> None:
        if os.getpid() != self._pid:
            return  # a forked DataLoader worker: the training process decides when to stop
        name = signal.Signals(signum).name
        first = self.received is None
        if first:
            self.received = signum
        if self.saving:
            notice(
                f"vqtouch: {name} received while writing a checkpoint; stopping once it is complete "
                "(kill -9 stops at once, keeping the last complete checkpoint)"
            )
        elif first:
            notice(f"vqtouch: {name} received; stopping after the current step, once its checkpoint is written")
        else:
            notice(
                f"vqtouch: {name} received again; still finishing the current step and its checkpoint "
                "(kill -9 stops at once, keeping the last complete checkpoint)"
            )


@dataclass
class DistributedContext:
    """Rank and world size; world 1 when not launched by torchrun."""

    rank: int = 0
    world: int = 1

    @property
    def is_main(self) -> bool:
        """Whether this process writes files and shows progress."""
        return self.rank == 0

    @classmethod
    def from_environment(cls, device: torch.device) -> DistributedContext:
        """Join the process group torchrun set up (WORLD_SIZE > 1), else a single process."""
        world = int(os.environ.get("WORLD_SIZE", "1"))
        if world <= 1:
            return cls()
        import torch.distributed as dist

        if not dist.is_initialized():
            dist.init_process_group(backend="nccl" if device.type == "cuda" else "gloo")
            atexit.register(close_process_group)
        return cls(dist.get_rank(), dist.get_world_size())


def close_process_group() -> None:
    """Tear the process group down before the interpreter does: left to exit, gloo's threads can abort
    a rank ("terminate called without an active exception"), and a rank that tears down while another
    still talks to it aborts that one, hence the barrier first (bounded, so a rank whose partner died
    still exits)."""
    import torch.distributed as dist

    if not dist.is_initialized():
        return
    with contextlib.suppress(Exception):
        if dist.get_backend() == "gloo":
            dist.monitored_barrier(timeout=datetime.timedelta(seconds=60))
        else:
            dist.barrier()
    with contextlib.suppress(Exception):
        dist.destroy_process_group()

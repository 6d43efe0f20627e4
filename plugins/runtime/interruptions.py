"""What a training command stopped by Ctrl-C or SIGTERM says and the exit status it returns."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .run_dir import RunDir


def interrupted_message(exc: BaseException, run: RunDir, command: str) -> str:
    """What a ``vqtouch train COMMAND`` that was stopped by Ctrl-C or SIGTERM tells the user: the
    checkpoint the trainer wrote (:class:`~vqtouch.plugins.training.trainer.TrainingInterrupted`), else the
    run's newest complete one, else that nothing was saved; never a claim it cannot back."""
    from vqtouch.plugins.training.trainer import TrainingInterrupted
    from vqtouch.plugins.training.checkpoints import latest_checkpoint

    resume = f"vqtouch train {command} --resume {run.path}"
    if isinstance(exc, TrainingInterrupted) and exc.checkpoint is not None:
        return f"vqtouch: {exc}; resume with: {resume}"
    folder = latest_checkpoint(run.checkpoints)
    cause = str(exc) if isinstance(exc, TrainingInterrupted) else "interrupted"
    if folder is not None:
        return f"vqtouch: {cause}; the run's last complete checkpoint is {folder}; resume with: {resume}"
    return (
        f"vqtouch: {cause} before any checkpoint was written; nothing to resume: start again with "
        f"--overwrite --out {run.path}"
    )


def interrupted_status(exc: BaseException) -> int:
    """The exit status of a command stopped by ``exc``: 128 + the signal's number, as a shell reports a
    process killed by that signal (143 for SIGTERM, which schedulers read as "terminated"), and
    130 (Ctrl-C) for any other interruption."""
    import signal as signals

    from vqtouch.plugins.training.trainer import TrainingInterrupted

    if isinstance(exc, TrainingInterrupted) and exc.cause in signals.Signals.__members__:
        return 128 + signals.Signals[exc.cause].value
    if isinstance(getattr(exc, "signum", None), int):  # SIGTERM outside training (vqtouch.plugins.cli.app.Terminated)
        return 128 + exc.signum
    return 130

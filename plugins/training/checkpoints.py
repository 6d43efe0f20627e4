"""A run's step folders: which is the newest good one, what the trainer stored in it, and its EMA weights.

The newest complete, readable folder is the one source of truth (there is no ``latest`` pointer
file); newer incomplete or damaged folders are skipped with a :class:`SkippedCheckpointWarning`.
"""

from __future__ import annotations

import json
import re
import warnings
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import torch
from safetensors import safe_open
from torch import nn

from vqtouch.core.checkpoint import atomic_write
from vqtouch.core.errors import CheckpointError, VqtouchWarning

TRAINER_STATE = "trainer_state.safetensors"
STEP_FOLDER = re.compile(r"step-(\d+)")


class SkippedCheckpointWarning(VqtouchWarning):
    """A checkpoint folder was skipped because it is incomplete or unreadable (the message says why)."""


def first_line(exc: BaseException) -> str:
    """The first line of an exception's message (its type name when the message is empty)."""
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


def _as_clause(problem: str | None) -> str:
    # checkpoint_problem's phrases ("no X: ...", "X is missing") after "the newest, step-N,".
    if problem is None:
        return "is complete"
    return f"has {problem}" if problem.startswith("no ") else f"is unusable: {problem}"


def no_good_checkpoint(checkpoint_dir: Path, required_files: Iterable[str] = ()) -> str:
    """``DIR: holds N checkpoint folder(s) but no complete one (the newest, step-N, has ...)``: why a
    run's step folders give nothing to read (for when :func:`latest_good_checkpoint` found none);
    callers add what to do."""
    folders = step_folders(checkpoint_dir)
    newest = folders[-1][1]
    return (
        f"{checkpoint_dir}: holds {len(folders)} checkpoint folder(s) but no complete one (the newest, "
        f"{newest.name}, {_as_clause(checkpoint_problem(newest, required_files))})"
    )


def step_folders(checkpoint_dir: Path) -> list[tuple[int, Path]]:
    """The ``step-N`` folders under ``checkpoint_dir`` as (step, folder), oldest first, complete or not.

    Ordered by the number, not the name (``step-100000000`` is newer than ``step-99999999``).
    """
    try:
        entries = list(Path(checkpoint_dir).iterdir())
    except OSError:  # missing, or not a folder
        return []
    folders = []
    for entry in entries:
        found = STEP_FOLDER.fullmatch(entry.name)
        if found and entry.is_dir():
            folders.append((int(found.group(1)), entry))
    return sorted(folders, key=lambda item: item[0])


def _unreadable(path: Path) -> str | None:
    """Why ``path`` is not a readable checkpoint file, or None: safe_open checks the safetensors
    header and that the file is as long as the header says; a vqtouch component header must also
    carry a parsable config and a step number (what :func:`vqtouch.core.load` needs)."""
    try:
        with safe_open(str(path), framework="pt") as handle:
            metadata = handle.metadata() or {}
    except Exception as exc:  # noqa: BLE001 - safetensors raises several error types
        return f"is not a readable safetensors file ({first_line(exc)})"
    if "vqtouch.component" in metadata:
        step = metadata.get("vqtouch.step", "0")
        if not step.isdecimal():
            return f"has a damaged vqtouch header (vqtouch.step is {step!r}, not a step number)"
        try:
            json.loads(metadata["vqtouch.config"])
        except (KeyError, json.JSONDecodeError):
            return "has a damaged vqtouch header (no readable vqtouch.config)"
    return None


def read_trainer_meta(folder: Path) -> dict[str, Any]:
    """The JSON the trainer stored in a step folder's trainer state (step, best step, optimizer
    settings, ...); CheckpointError naming the file when it cannot be read."""
    path = Path(folder) / TRAINER_STATE
    try:
        with safe_open(str(path), framework="pt") as handle:
            return json.loads((handle.metadata() or {})["vqtouch.trainer"])
    except Exception as exc:  # noqa: BLE001 - safetensors, JSON and key errors alike
        raise CheckpointError(f"{path}: unreadable trainer state ({first_line(exc)})") from None


def saved_ema_weights(folder: Path) -> dict[str, dict[str, torch.Tensor]]:
    """The exponential moving average of each module's floating-point weights that the trainer kept
    in step ``folder`` (``train.ema_decay``), by module name; empty when the run kept none.  One read
    of the trainer state; CheckpointError naming the file when it cannot be read."""
    path = Path(folder) / TRAINER_STATE
    averages: dict[str, dict[str, torch.Tensor]] = {}
    try:
        with safe_open(str(path), framework="pt") as handle:
            for key in handle.keys():
                if key.startswith("ema."):
                    module_name, tensor_name = key[len("ema.") :].split(".", 1)
                    averages.setdefault(module_name, {})[tensor_name] = handle.get_tensor(key)
    except Exception as exc:  # noqa: BLE001 - safetensors raises several error types
        raise CheckpointError(f"{path}: unreadable trainer state ({first_line(exc)})") from None
    return averages


def apply_ema_weights(module: nn.Module, ema_KT: Mapping[str, torch.Tensor], where: str | Path) -> None:
    """Replace ``module``'s floating-point weights by their moving average ``ema_KT`` (from
    :func:`saved_ema_weights` or :attr:`Trainer.ema`); integer buffers keep their values.  A key the
    module lacks, a floating tensor the average lacks, a wrong shape or a non-finite value is a
    one-line CheckpointError naming ``where``: sampling with half-replaced weights would be garbage."""
    state = module.state_dict()
    floating = {key for key, value in state.items() if value.dtype.is_floating_point}
    unexpected = sorted(set(ema_KT) - set(state))
    missing = sorted(floating - set(ema_KT))
    if unexpected or missing:
        problem = f"unexpected {unexpected[0]!r}" if unexpected else f"missing {missing[0]!r}"
        raise CheckpointError(f"{where}: its EMA weights do not fit the model ({problem}); sample with the raw weights")
    for key, value in ema_KT.items():  # all checked before any is copied
        if tuple(value.shape) != tuple(state[key].shape):
            raise CheckpointError(
                f"{where}: EMA tensor {key!r} has shape {tuple(value.shape)}, the model {tuple(state[key].shape)}"
            )
        if not torch.isfinite(value).all():
            raise CheckpointError(f"{where}: EMA tensor {key!r} holds NaN or Inf; sample with the raw weights")
    with torch.no_grad():
        for key, value in ema_KT.items():
            state[key].copy_(value.to(state[key].dtype))


def checkpoint_problem(folder: Path, required_files: Iterable[str] = ()) -> str | None:
    """Why the step folder ``folder`` cannot be used, in a few words, or None when it is complete and
    readable: a readable trainer state, and every module file it lists plus ``required_files``
    present and a readable safetensors file (headers are read, tensors are not)."""
    state = folder / TRAINER_STATE
    if not state.is_file():
        return f"no {TRAINER_STATE}: its save was interrupted"
    try:
        with safe_open(str(state), framework="pt") as handle:
            meta = json.loads((handle.metadata() or {})["vqtouch.trainer"])
        modules = [f"{name}.safetensors" for name in meta.get("modules", [])]
    except Exception as exc:  # noqa: BLE001 - safetensors, JSON and key errors alike
        # Phrased like read_trainer_meta's error, which resume raises for the same file.
        return f"{TRAINER_STATE} is unreadable ({first_line(exc)})"
    for name in dict.fromkeys([*modules, *required_files]):
        if not (folder / name).is_file():
            return f"{name} is missing"
        why = _unreadable(folder / name)
        if why is not None:
            return f"{name} {why}"
    return None


def latest_good_checkpoint(checkpoint_dir: Path, required_files: Iterable[str] = ()) -> Path | None:
    """The newest ``step-*`` folder under ``checkpoint_dir`` that is complete and readable (see
    :func:`checkpoint_problem`), or None; the one function every reader of a run's latest
    checkpoint should use.

    When a good folder is found, each newer folder skipped on the way gets one
    :class:`SkippedCheckpointWarning` naming it and why (when none is good, the caller's error
    says so once).  ``required_files`` are the files the caller needs (e.g. the tokenizer's
    ``autoencoder.safetensors`` and ``quantizer.safetensors``).
    """
    required_files = tuple(required_files)
    skipped = []
    for _, folder in reversed(step_folders(checkpoint_dir)):
        problem = checkpoint_problem(folder, required_files)
        if problem is None:
            for message in skipped:
                warnings.warn(message, SkippedCheckpointWarning, stacklevel=2)
            return folder
        skipped.append(f"checkpoint {folder} skipped: {problem}")
    return None


def latest_checkpoint(checkpoint_dir: Path) -> Path | None:
    """The newest ``step-*`` folder that holds a trainer state, or None (a quick look that reads no
    file; :func:`latest_good_checkpoint` also checks the files and says what it skips)."""
    complete = [folder for _, folder in step_folders(checkpoint_dir) if (folder / TRAINER_STATE).is_file()]
    return complete[-1] if complete else None


def rewind_metrics(path: Path, stage: str, step: int) -> int:
    """Drop the lines of ``stage`` logged after ``step`` from a run's metrics.jsonl; returns how many.

    A resumed run logs those steps again, so keeping them would give duplicate lines and
    steps that go backwards.  Other stages' lines are kept, and so are lines that are not
    JSON, except a last line without its newline (an append cut short by a kill).  The file
    is rewritten atomically, and only when something changes.
    """
    path = Path(path)
    if not path.is_file():
        return 0
    kept, dropped, changed = [], 0, False
    for line in path.read_text(encoding="utf-8").splitlines(keepends=True):
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            record = None
            if not line.endswith("\n"):
                dropped, changed = dropped + 1, True
                continue
        if (
            isinstance(record, dict)
            and record.get("stage") == stage
            and isinstance(record.get("step"), int)
            and record["step"] > step
        ):
            dropped, changed = dropped + 1, True
            continue
        if not line.endswith("\n"):
            line, changed = line + "\n", True
        kept.append(line)
    if changed:
        text = "".join(kept)
        atomic_write(path, lambda tmp: tmp.write_text(text, encoding="utf-8"))
    return dropped

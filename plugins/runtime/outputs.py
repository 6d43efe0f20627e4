"""Where a command may write: the output rule, in one place.

A command never writes into, replaces or empties what it reads (an input file or folder, a run
or any folder inside it, a families or adapt output, a bundle), nor anything inside the installed
vqtouch package (``pretrained export``, which writes bundles there, says so explicitly).
``--overwrite`` only ever replaces an earlier output of the same command.

The command line (:mod:`vqtouch.plugins.cli.app`) records every path a parsed command names
(:func:`command_inputs`) for as long as the command runs (:func:`reading`); every place that
creates an output (:func:`staged_output`, :meth:`vqtouch.plugins.runtime.run_dir.RunDir.create`, and the
commands' folders through :func:`check_output`) refuses a folder that is, holds or lies inside
one of them, in one line naming the option, before anything is written or emptied.  A library
caller passes what it reads as ``reads`` (``(flag, what, path)`` triples).
"""

from __future__ import annotations

import argparse
import contextlib
import contextvars
import importlib
import json
import os
import shutil
import tempfile
import warnings
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from vqtouch.core.errors import ConfigError, VqtouchWarning

#: The lock file inside a run (see :mod:`vqtouch.plugins.runtime.run_dir`); it stays after the run (removing it would
#: let two processes lock two different files of the same name).  Only RunDir makes it, so it also
#: marks a run directory whose config.json is not written yet.
LOCK_NAME = ".vqtouch.lock"
#: The file in every staged output that names the command which wrote it: what ``--overwrite`` checks.
MARKER_NAME = ".vqtouch-output.json"
#: The packages whose folders no output may touch.
PACKAGES = ("core", "plugins", "conditioners", "sensors")
#: Options that name what a command writes, never what it reads.
OUTPUT_DESTS = frozenset({"out", "resume"})
#: Config keys (``--set KEY=PATH``) that name where a command writes.
OUTPUT_KEYS = frozenset({"output_dir"})

Read = tuple[str, str, "str | Path | None"]


@dataclass(frozen=True)
class CommandContext:
    """What the running command reads, and its name (``fewshot``, ``evaluate mix-ratio``)."""

    command: str = ""
    reads: tuple[Read, ...] = ()


_CURRENT: contextvars.ContextVar[CommandContext] = contextvars.ContextVar("vqtouch_command", default=CommandContext())


@contextlib.contextmanager
def reading(reads: Iterable[Read], command: str = "") -> Iterator[None]:
    """While the block runs, every output is also checked against ``reads`` (the command line's)."""
    token = _CURRENT.set(CommandContext(command, tuple(reads)))
    try:
        yield
    finally:
        _CURRENT.reset(token)


def current_command() -> str:
    """The name of the command being run (empty outside the command line)."""
    return _CURRENT.get().command


def _path_candidates(text: str) -> list[str]:
    """The paths a parsed value may name: itself, a JSON block's strings, a ``KEY=VALUE``'s value."""
    text = text.strip()
    if text.startswith("{"):
        try:
            block = json.loads(text)
        except json.JSONDecodeError:
            return []
        found: list[str] = []

        def walk(value: Any) -> None:
            if isinstance(value, str):
                found.append(value)
            elif isinstance(value, dict):
                for item in value.values():
                    walk(item)
            elif isinstance(value, list):
                for item in value:
                    walk(item)

        walk(block)
        return found
    key, equals, value = text.partition("=")
    if equals and key.strip().rsplit(".", 1)[-1] in OUTPUT_KEYS:
        return []
    return [text, value] if equals else [text]


def _subcommand_actions(parser: argparse.ArgumentParser, args: argparse.Namespace) -> tuple[list[str], list]:
    """The chosen subcommand's words and argparse actions, following ``args``' subcommand choices."""
    words: list[str] = []
    actions = list(parser._actions)
    while True:
        subs = [action for action in actions if isinstance(action, argparse._SubParsersAction)]
        chosen = getattr(args, subs[0].dest, None) if subs else None
        if chosen is None or chosen not in subs[0].choices:
            return words, actions
        words.append(chosen)
        actions = [action for action in actions if action is not subs[0]] + list(subs[0].choices[chosen]._actions)


def command_inputs(parser: argparse.ArgumentParser, args: argparse.Namespace) -> tuple[str, list[Read]]:
    """The parsed command's name and every existing file or folder its options name (``--run``,
    ``--images``, ``--families``, a JSON block's ``root``, ``--set KEY=PATH``, ...), except the outputs
    (``--out``, ``--resume`` and what a command names in its ``output_options`` default, e.g.
    ``pretrained export --root``)."""
    words, actions = _subcommand_actions(parser, args)
    outputs = OUTPUT_DESTS | set(getattr(args, "output_options", ()))
    flags = {
        action.dest: (action.option_strings[-1] if action.option_strings else action.metavar or action.dest)
        for action in actions
    }
    reads: list[Read] = []
    for dest, value in vars(args).items():
        if dest not in flags or dest in outputs:  # only what the user can give: not a parser's own defaults
            continue
        for text in value if isinstance(value, (list, tuple)) else [value]:
            if not isinstance(text, str) or not text:
                continue
            for candidate in _path_candidates(text):
                if candidate and not candidate.startswith("pretrained:") and os.path.exists(candidate):
                    reads.append((str(flags.get(dest, dest)), "input", candidate))
    return " ".join(words), reads


def package_folders() -> list[Path]:
    """The installed vqtouch package's folders (the checkout's, for an editable install)."""
    folders = []
    for name in PACKAGES:
        module = importlib.import_module(f"vqtouch.{name}")
        folders.append(Path(module.__file__).resolve().parent)
    return folders


def check_output(out: str | Path, reads: Sequence[Read] = (), *, into_package: bool = False) -> Path:
    """``out`` resolved, after refusing in one line (ConfigError) a folder that is one of the command's
    inputs (``reads`` and the command line's), holds one or lies inside one, or that is, holds or lies
    inside the installed package (unless ``into_package``: ``pretrained export``'s bundles)."""
    target = Path(out).expanduser().resolve()
    for flag, what, path in (*reads, *_CURRENT.get().reads):
        if path is None or str(path).startswith("pretrained:"):
            continue
        source = Path(path).expanduser().resolve()
        named = f"{flag} {path}" if what == "input" else f"the {what} this command reads ({flag} {path})"
        rule = "a command never writes into what it reads"
        if source == target:
            raise ConfigError(f"--out {out} is {named}; {rule}: choose another --out")
        if source.is_relative_to(target):
            raise ConfigError(f"--out {out} holds {named}; {rule}: choose another --out")
        if source.is_dir() and target.is_relative_to(source):
            raise ConfigError(f"--out {out} is inside {named}; {rule}: choose a folder outside it")
    if not into_package:
        for folder in package_folders():
            if target.is_relative_to(folder) or folder.is_relative_to(target):
                raise ConfigError(
                    f"--out {out} is or holds the installed vqtouch package's folder {folder}; write outputs elsewhere"
                )
    return target


def _holder_alive(staged: Path) -> bool:
    """Whether the process that named a staging folder ``.OUT.<pid>.XXXX.partial`` still runs."""
    parts = staged.name.split(".")
    pid = parts[-3] if len(parts) >= 4 else ""
    if not pid.isdigit():
        return False
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def clean_leftovers(out: Path) -> list[Path]:
    """Remove the staging folders that an earlier, killed call left beside ``out`` (its process is
    gone); returns them.  Folders of a call still running are left alone."""
    removed = []
    if not out.parent.is_dir():
        return removed
    for leftover in out.parent.glob(f".{out.name}.*"):
        if leftover.suffix in {".partial", ".replaced"} and leftover.is_dir() and not _holder_alive(leftover):
            shutil.rmtree(leftover, ignore_errors=True)
            removed.append(leftover)
    if removed:
        warnings.warn(
            f"removed {len(removed)} unfinished output folder(s) beside {out} that a stopped earlier call left",
            VqtouchWarning,
            stacklevel=3,
        )
    return removed


def previous_output_of(out: Path) -> str | None:
    """The command that wrote ``out`` (its marker file), or None."""
    try:
        return str(json.loads((out / MARKER_NAME).read_text(encoding="utf-8"))["command"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _refuse_foreign_overwrite(out: Path, command: str, recognise: Callable[[Path], bool] | None) -> None:
    if recognise is not None and recognise(out):
        return
    made_by = previous_output_of(out)
    if made_by == command:
        return
    said = f"`vqtouch {made_by}`" if made_by else "no vqtouch command (it has no " + MARKER_NAME + ")"
    raise ConfigError(
        f"--out {out} holds files written by {said}; --overwrite only replaces an earlier output of "
        f"`vqtouch {command}`: choose another --out, or empty that folder yourself"
    )


@contextlib.contextmanager
def staged_output(
    out: str | Path,
    *,
    overwrite: bool = False,
    reads: Sequence[Read] = (),
    command: str | None = None,
    into_package: bool = False,
    recognise: Callable[[Path], bool] | None = None,
) -> Iterator[Path]:
    """The output folder of a command that is not a run (``generate --out``, ...): yields a fresh hidden
    folder beside ``out`` to write into, and moves it onto ``out`` whole when the block ends, so ``out``
    is never half-written, never mixes two calls' files and keeps its old content until the new one is
    complete.

    Refused in one line before anything is written: ``out`` breaks the output rule
    (:func:`check_output`), is a file or a run directory, or holds files and ``overwrite`` is not set
    or they are not an earlier output of ``command`` (default: the command line's; its marker file,
    or ``recognise(out)``).  An error or Ctrl-C in the block (or SIGTERM, which ``vqtouch.plugins.cli.app``
    turns into one) removes the staged folder; a killed call's folder is removed by the next call.
    When another process filled ``out`` meanwhile, the staged files are kept and the error says where.
    """
    out = Path(out)
    check_output(out, reads, into_package=into_package)
    command = command if command is not None else current_command() or "library"
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out} is a file; give a folder")
    if (out / "config.json").is_file() or (out / LOCK_NAME).exists():
        raise ConfigError(f"--out {out} is a vqtouch run; write this command's output to another folder")
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            raise ConfigError(
                f"--out {out} already holds files; choose another --out, or pass --overwrite to replace them"
            )
        _refuse_foreign_overwrite(out, command, recognise)
    out.parent.mkdir(parents=True, exist_ok=True)
    clean_leftovers(out)
    staged = Path(tempfile.mkdtemp(prefix=f".{out.name}.{os.getpid()}.", suffix=".partial", dir=out.parent))
    try:
        (staged / MARKER_NAME).write_text(json.dumps({"command": command}) + "\n", encoding="utf-8")
        yield staged
    except BaseException:  # an error, Ctrl-C, or SIGTERM (which the command line turns into an interruption)
        shutil.rmtree(staged, ignore_errors=True)
        raise
    _move_into_place(staged, out, overwrite)


def _move_into_place(staged: Path, out: Path, overwrite: bool) -> None:
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            raise ConfigError(
                f"--out {out} was filled by another process meanwhile; this command's output is in {staged}"
            )
        retired = Path(tempfile.mkdtemp(prefix=f".{out.name}.{os.getpid()}.", suffix=".replaced", dir=out.parent))
        os.replace(out, retired / out.name)
        os.replace(staged, out)
        shutil.rmtree(retired, ignore_errors=True)
    else:
        os.replace(staged, out)  # onto a missing or empty folder


def output_folder(out: str | Path, reads: Sequence[Read] = ()) -> Path:
    """``out`` created as a folder after the output rule's check (:func:`check_output`): for the
    outputs that are written in place rather than staged (an experiment that resumes its arms, a
    stage's folder inside its run)."""
    check_output(out, reads)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out} is a file; give a folder")
    out.mkdir(parents=True, exist_ok=True)
    return out

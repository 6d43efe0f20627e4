"""What the fault-injection tests check after a command, importable as ``import cli_checks``
(registered in conftest): that it failed in one line, that it left a folder as it was, and every
command the parser has."""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from pathlib import Path


def one_error_line(capsys) -> str:
    """The single stderr line of a failed command, without its prefix (asserts it is one line)."""
    err = capsys.readouterr().err
    assert err.startswith("vqtouch: error: ") and err.count("\n") == 1, err
    return err[len("vqtouch: error: ") :].rstrip("\n")


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` and its bytes: equal snapshots mean nothing was written there."""
    return {str(path.relative_to(folder)): path.read_bytes() for path in sorted(folder.rglob("*")) if path.is_file()}


def leaf_commands(
    parser: argparse.ArgumentParser, words: tuple[str, ...] = ()
) -> Iterator[tuple[tuple[str, ...], argparse.ArgumentParser]]:
    """``(words, parser)`` of every leaf command of the ``vqtouch`` parser (``("evaluate", "pairs")``, ...)."""
    subs = [action for action in parser._actions if isinstance(action, argparse._SubParsersAction)]
    if not subs:
        yield words, parser
        return
    for name, sub in subs[0].choices.items():
        yield from leaf_commands(sub, (*words, name))

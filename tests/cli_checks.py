"""What the fault-injection tests check after a command, importable as ``import cli_checks``
(registered in conftest): that it failed in one line, and that it left a folder as it was."""

from __future__ import annotations

from pathlib import Path


def one_error_line(capsys) -> str:
    """The single stderr line of a failed command, without its prefix (asserts it is one line)."""
    err = capsys.readouterr().err
    assert err.startswith("vqtouch: error: ") and err.count("\n") == 1, err
    return err[len("vqtouch: error: ") :].rstrip("\n")


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` and its bytes: equal snapshots mean nothing was written there."""
    return {str(path.relative_to(folder)): path.read_bytes() for path in sorted(folder.rglob("*")) if path.is_file()}

"""How the ``vqtouch`` command line reports what went wrong: a user error as one line (an OSError with
what to do about it), every warning as one line, the ``--debug`` switch, and a stdout closed by
the reader (``vqtouch plugins | head``)."""

from __future__ import annotations

import errno
import json
import os
import stat
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from vqtouch.core.errors import VqtouchError, VqtouchWarning, one_line

ENV_DEBUG = "VQTOUCH_DEBUG"

#: What to do about an OSError, by errno; the message already names the file and the error.
#: Most come from creating a run's folder, hence the pointers to --out and output_dir.
_WRITE_ELSEWHERE = "write the run elsewhere (--out or output_dir)"
_OS_ERROR_HINTS = {
    errno.EACCES: f"fix its permissions, or {_WRITE_ELSEWHERE}",
    errno.EPERM: f"fix its permissions, or {_WRITE_ELSEWHERE}",
    errno.EROFS: _WRITE_ELSEWHERE,
    errno.ENOSPC: f"the disk is full: free space, or {_WRITE_ELSEWHERE}",
    errno.EDQUOT: f"the disk quota is used up: free space, or {_WRITE_ELSEWHERE}",
    errno.EEXIST: "a file is in the way where a folder is needed: remove it or choose another path",
    errno.ENOTDIR: "part of the path is a file, not a folder: choose another path",
    errno.EISDIR: "it is a folder where a file is needed: give the path of a file",
    errno.ENOENT: "check the path: a part of it does not exist",
}


def _debug_requested(argv: Sequence[str]) -> bool:
    """``--debug`` among the global options (before the command), or ``VQTOUCH_DEBUG`` set and not 0.

    Read from argv rather than the parsed arguments: loading plugins, which may fail, comes
    before parsing.
    """
    if os.environ.get(ENV_DEBUG, "").strip() not in {"", "0"}:
        return True
    for token in argv:
        if not token.startswith("-"):  # the command: what follows belongs to it
            return False
        if token == "--debug":
            return True
    return False


def _os_error_message(exc: OSError) -> str:
    """``FILE: strerror; what to do`` for an OSError (creating a run, reading a file, ...)."""
    if exc.filename is None:  # no file to name (e.g. one carried out of a DataLoader worker)
        return one_line(str(exc)) + " (run with --debug for the traceback)"
    where = str(exc.filename) + (f" -> {exc.filename2}" if exc.filename2 is not None else "")
    hint = _OS_ERROR_HINTS.get(exc.errno, "run with --debug for the traceback")
    return f"{where}: {exc.strerror or one_line(str(exc))}; {hint}"


def user_error_message(exc: BaseException) -> str | None:
    """The one-line message of an error the user can fix, or None for a bug (which keeps its traceback).

    Besides :class:`VqtouchError`: OSError (an output folder that cannot be created, a file that
    cannot be read) and a JSON file that does not parse (e.g. a run's damaged config.json).
    """
    if isinstance(exc, VqtouchError):
        return one_line(str(exc))
    if isinstance(exc, OSError):
        return _os_error_message(exc)
    if isinstance(exc, json.JSONDecodeError):
        # The decoder does not know the file; the callers that read run files name it themselves.
        return (
            f"a JSON file is not valid JSON ({exc.msg}: line {exc.lineno} column {exc.colno}); if it is a run's "
            "config.json or env.json, restore it from a copy (run with --debug to see which file)"
        )
    return None


def _silence_stdout() -> None:
    """After a closed pipe on stdout: point stdout at /dev/null so that flushing it at exit does not
    fail again (the recipe of Python's documentation on SIGPIPE)."""
    try:
        fd = sys.stdout.fileno()
        # Only a pipe: main() may run inside a process whose stdout is a file or a terminal, which a
        # BrokenPipeError from elsewhere must not silence for good.
        if stat.S_ISFIFO(os.fstat(fd).st_mode):
            os.dup2(os.open(os.devnull, os.O_WRONLY), fd)
    except (OSError, ValueError, AttributeError):  # stdout replaced by an object without a descriptor
        pass


def _show_warning(
    message: Warning | str,
    category: type[Warning],
    filename: str,
    lineno: int,
    file: Any = None,
    line: str | None = None,
) -> None:
    """Every warning as one line on stderr: vqtouch's own as they are, a library's (matplotlib, torch, ...)
    with its category and module, never its source line.  ``--debug`` shows them as Python does."""
    if issubclass(category, VqtouchWarning):
        text = one_line(str(message))
    else:
        module = Path(filename).stem if filename else "?"
        text = f"{one_line(str(message))} ({category.__name__} from {module})"
    print(f"vqtouch: warning: {text}", file=sys.stderr if file is None else file)

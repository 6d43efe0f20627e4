"""Exceptions raised by vqtouch.

Every error a user can trigger derives from :class:`VqtouchError`; the CLI prints it as
one line (``vqtouch: error: ...``, see :func:`one_line`) and exits with status 2 instead of
showing a traceback (``--debug`` or ``VQTOUCH_DEBUG=1`` show it).
"""

from __future__ import annotations

import difflib
import re
from collections.abc import Iterable
from typing import Any


class VqtouchError(Exception):
    """Base class of every user-facing vqtouch error (the message says how to fix it)."""


class PluginError(VqtouchError):
    """A plugin failed to load, registered something twice, or broke the registration contract."""


class UnknownPluginError(VqtouchError, KeyError):
    """A name was looked up in a registry that has no such entry."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0]) if self.args else ""


class ConfigError(VqtouchError):
    """An experiment configuration is malformed or names an impossible combination."""


class CheckpointError(VqtouchError):
    """A checkpoint file is missing, corrupted, not safetensors, or does not fit the model."""


class DatasetError(VqtouchError):
    """A dataset folder, list or image is missing, malformed, or inconsistent (names the file)."""


class MissingWeightsError(VqtouchError):
    """Pretrained weights that a component needs were not provided as a local file."""


class NothingToEvaluateError(VqtouchError):
    """An evaluation was given no samples (e.g. the held-out split of ``data.val_fraction=0``).

    A distinct class so that a stage can skip its evaluation and say why instead of failing
    after the training it has done.
    """


class VqtouchWarning(UserWarning):
    """Base class of the warnings vqtouch gives a user (something was skipped, the message says
    what and why); the CLI prints each as one line, ``vqtouch: warning: ...``."""


class VqtouchDeprecationWarning(VqtouchWarning, FutureWarning):
    """An old name still works but will be removed (see :mod:`vqtouch.core.deprecations`).  A
    FutureWarning, so Python shows it to users by default, as timm and diffusers do."""


# PyTorch re-raises an exception from a DataLoader worker as the same type, but with the
# worker's whole traceback as its message; the original message is its last line.
_WORKER_ERROR = re.compile(
    r"Caught (?P<type>\w+) in DataLoader worker process \d+\.\s*\n"
    r"Original Traceback \(most recent call last\):\n.*\n(?:[\w.]+\.)?(?P=type): (?P<message>[^\n]*)\s*\Z",
    re.DOTALL,
)


def one_line(message: str) -> str:
    """``message`` as the one line a user error promises.

    An error that PyTorch carried out of a DataLoader worker gets back its original message
    (the copy of the worker's traceback is dropped); any other line breaks become ``"; "``.
    """
    message = _WORKER_ERROR.sub(lambda match: match["message"], message)
    return "; ".join(line.strip() for line in message.splitlines() if line.strip())


def closest_match(name: str, candidates: Iterable[str]) -> str | None:
    """Return the candidate most similar to ``name`` (or None when nothing is close)."""
    matches = difflib.get_close_matches(name, list(candidates), n=1, cutoff=0.5)
    return matches[0] if matches else None


def unknown_name_message(kind: str, name: str, available: Iterable[str]) -> str:
    """Build the standard 'unknown X' message: what was asked, what exists, what is closest."""
    available = sorted(available)
    listing = ", ".join(available) if available else "(none installed)"
    message = f"unknown {kind} {name!r}; available: {listing}"
    suggestion = closest_match(name, available)
    if suggestion is not None:
        message += f"; did you mean {suggestion!r}?"
    return message


def format_validation_error(exc: Any, prefix: str = "") -> str:
    """One line per problem: the dotted path, what is wrong and the offending value."""
    problems = []
    for error in exc.errors(include_url=False):
        loc = ".".join(str(part) for part in (prefix, *error["loc"]) if part != "")
        message = error["msg"]
        if error["type"] not in {"unknown_plugin", "unknown_option", "missing", "repeated_stage", "no_plugin_host"}:
            shown = repr(error.get("input"))
            message += f" (got {shown if len(shown) <= 60 else shown[:57] + '...'})"
        problems.append(f"{loc or '<root>'}: {message}")
    if len(problems) == 1:
        return f"invalid configuration: {problems[0]}"
    return f"invalid configuration ({len(problems)} problems): " + "; ".join(problems)

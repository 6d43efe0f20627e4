"""Lazy references to a plugin's implementation: ``"package.module:attribute"``.

A plugin module is imported whenever plugins load, which every command does, ``vqtouch --help``
included.  So that listing, validating and printing configs never import torch, a plugin may
register its factory, its stage's ``run`` or its command's handler as a reference string instead
of the object; the object's module is imported the first time it is used (the same form as a
Python entry point's value).  Callables are accepted everywhere a reference is.
"""

from __future__ import annotations

import importlib
import re
from typing import Any

from .errors import PluginError

#: ``package.module:attribute`` (the attribute may be dotted: ``module:Class.method``).
_REFERENCE = re.compile(r"^[A-Za-z_]\w*(\.[A-Za-z_]\w*)*:[A-Za-z_]\w*(\.[A-Za-z_]\w*)*$")


def is_reference(value: Any) -> bool:
    """Whether ``value`` is a well-formed ``"package.module:attribute"`` string."""
    return isinstance(value, str) and _REFERENCE.match(value) is not None


def check_callable_or_reference(value: Any, what: str) -> None:
    """PluginError naming ``what`` unless ``value`` is callable or a well-formed reference."""
    if isinstance(value, str):
        if not is_reference(value):
            raise PluginError(f"{what} is {value!r}: give a callable or a 'package.module:attribute' reference")
    elif not callable(value):
        raise PluginError(f"{what} is not callable: give a callable or a 'package.module:attribute' reference")


def resolve(value: Any, what: str) -> Any:
    """The object ``value`` refers to (``value`` itself when it is not a reference string); an import
    failure or a missing attribute is a one-line PluginError naming ``what``."""
    if not isinstance(value, str):
        return value
    module_name, _, attribute = value.partition(":")
    try:
        target: Any = importlib.import_module(module_name)
        for part in attribute.split("."):
            target = getattr(target, part)
    except (ImportError, AttributeError) as exc:
        raise PluginError(f"{what} {value!r} cannot be loaded: {type(exc).__name__}: {exc}") from exc
    if not callable(target):
        raise PluginError(f"{what} {value!r} is not callable")
    return target

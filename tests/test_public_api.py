"""The author-facing API of ``vqtouch.core`` (its ``__all__``): small, documented, typed."""

from __future__ import annotations

import inspect
import re
from pathlib import Path

import vqtouch.core as core

DOCS = Path(__file__).resolve().parents[1] / "docs" / "extending.md"


def _api_section() -> str:
    text = DOCS.read_text(encoding="utf-8")
    return text[text.index("### The API") : text.index("### Versions and renames")]


def test_the_api_is_small_and_every_name_resolves():
    names = [name for name in core.__all__ if name != "__version__"]
    assert 20 <= len(names) <= 27, len(names)
    assert len(set(names)) == len(names)
    for name in names:
        assert getattr(core, name) is not None


def test_every_api_name_is_documented_in_code_and_in_the_authors_guide():
    section = _api_section()
    for name in core.__all__:
        if name == "__version__":
            continue
        value = getattr(core, name)
        assert inspect.getdoc(value), f"vqtouch.core.{name} has no docstring"
        assert re.search(rf"`{re.escape(name)}`", section), f"docs/extending.md (The API) does not list {name}"


def test_the_api_takes_a_typed_plugin_host():
    for name in core.__all__:
        value = getattr(core, name)
        if not callable(value) or name == "__version__":
            continue
        targets = (
            [value]
            if not inspect.isclass(value)
            else [member for _, member in inspect.getmembers(value) if inspect.isfunction(member)]
        )
        for target in targets:
            parameter = inspect.signature(target).parameters.get("host")
            if parameter is not None:
                assert "PluginHost" in str(parameter.annotation), f"{name}.{target.__name__}: host is not typed"

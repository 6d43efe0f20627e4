"""The command and config reference pages (docs/reference/) are generated from the code and kept current."""

from __future__ import annotations

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def reference_module():
    spec = importlib.util.spec_from_file_location("make_reference", ROOT / "docs" / "make_reference.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_reference_pages_match_the_code():
    pages = reference_module().pages()
    stale = [name for name, text in pages.items() if (ROOT / "docs" / "reference" / name).read_text() != text]
    assert not stale, f"docs/reference/{', '.join(stale)} stale: run .venv/bin/python docs/make_reference.py"


def test_every_command_and_every_plugin_is_in_the_reference():
    from vqtouch.core import load_plugins
    from vqtouch.plugins.cli.app import build_parser

    module = reference_module()
    host = load_plugins(autoload=False)
    pages = module.pages()
    commands = {path for path, _, _ in walk(module, build_parser(host), "vqtouch")}
    assert {"vqtouch train generator", "vqtouch fewshot", "vqtouch evaluate downstream"} <= commands
    assert all(f"## `{path}`" in pages["commands.md"] for path in commands)
    for kind, registry in host.registries.items():
        for entry in registry:
            assert f"### `{entry.name}`" in pages["config.md"], (kind, entry.name)
    # A plugin option and an experiment key, each with its own description.
    assert "| `tokenizer.train.steps` |" in pages["config.md"]
    assert "| `--shots` SHOTS | images of the new sensor to learn from" in pages["commands.md"]


def walk(module, parser, path):
    yield path, parser, ""
    for name, sub, _ in module._subcommands(parser):
        yield from walk(module, sub, f"{path} {name}")

import hashlib
from pathlib import Path

import pytest

from vqtouch.core import MissingWeightsError
from vqtouch.plugins.utils.weights import WeightsSpec, resolve_weights

REPO = Path(__file__).resolve().parents[1]
SPEC = WeightsSpec(
    description="metric 'fid'",
    filenames=("inception.pth",),
    env_var="VQTOUCH_TEST_WEIGHTS",
    config_hint="--set evaluate.fid_weights=PATH",
    source_url="https://example.org/inception.pth",
)


@pytest.fixture(autouse=True)
def clean_env(monkeypatch):
    monkeypatch.delenv("VQTOUCH_TEST_WEIGHTS", raising=False)
    monkeypatch.delenv("VQTOUCH_WEIGHTS_DIR", raising=False)


def test_missing_everywhere_explains_all_three_ways():
    with pytest.raises(MissingWeightsError) as info:
        resolve_weights(SPEC)
    message = str(info.value)
    for needle in (
        "inception.pth",
        "https://example.org/inception.pth",
        "--set evaluate.fid_weights=PATH",
        "VQTOUCH_TEST_WEIGHTS=PATH",
        "VQTOUCH_WEIGHTS_DIR",
        "never downloads",
    ):
        assert needle in message


def test_resolution_order_explicit_then_env_then_dir(tmp_path, monkeypatch):
    explicit, from_env, folder = tmp_path / "a.pth", tmp_path / "b.pth", tmp_path / "dir"
    folder.mkdir()
    for path in (explicit, from_env, folder / "inception.pth"):
        path.write_bytes(b"w")
    monkeypatch.setenv("VQTOUCH_WEIGHTS_DIR", str(folder))
    assert resolve_weights(SPEC) == folder / "inception.pth"
    monkeypatch.setenv("VQTOUCH_TEST_WEIGHTS", str(from_env))
    assert resolve_weights(SPEC) == from_env
    assert resolve_weights(SPEC, explicit) == explicit


def test_explicit_path_that_does_not_exist(tmp_path):
    with pytest.raises(MissingWeightsError, match="does not exist"):
        resolve_weights(SPEC, tmp_path / "nope.pth")


def test_sha256_prefix_is_checked(tmp_path):
    path = tmp_path / "inception.pth"
    path.write_bytes(b"real weights")
    good = hashlib.sha256(b"real weights").hexdigest()[:8]
    checked = WeightsSpec(**{**SPEC.__dict__, "sha256_prefix": good})
    assert resolve_weights(checked, path) == path
    wrong = WeightsSpec(**{**SPEC.__dict__, "sha256_prefix": "00000000"})
    with pytest.raises(MissingWeightsError, match="corrupt or a different model"):
        resolve_weights(wrong, path)


# -- every WeightsSpec of the code base tells users a way to give the file that really exists ------


def _module_name(path):
    parts = path.relative_to(REPO).with_suffix("").parts
    return ".".join(("vqtouch", *(parts[:-1] if parts[-1] == "__init__" else parts)))


def _cli_options(parser):
    """Every ``--option`` of an argparse parser and of its subcommands."""
    import argparse

    options = set()
    for action in parser._actions:
        options.update(option for option in action.option_strings if option.startswith("--"))
        if isinstance(action, argparse._SubParsersAction):
            for subparser in action.choices.values():
                options |= _cli_options(subparser)
    return options


def _is_config_path(host, parts):
    """Whether ``--set a.b.c=...`` sets an existing option of ``host``'s experiment config.

    Sections are walked field by field; at a plugin slot the rest must be an option of
    one of that slot's plugins (after a list index for list slots).
    """
    from vqtouch.core.config import slots_of

    slots = slots_of(host.experiment_model)
    for cut in range(len(parts), 0, -1):
        slot = slots.get(".".join(parts[:cut]))
        if slot is None:
            continue
        rest = parts[cut:]
        if slot.many:
            if not rest or not rest[0].isdigit():
                return False
            rest = rest[1:]
        registry = host.registry(slot.kind)
        return len(rest) <= 1 and (
            not rest or any(rest[0] in registry.get(name).config_model.model_fields for name in registry.names())
        )
    model = host.experiment_model
    for part in parts:
        if not isinstance(model, type) or part not in getattr(model, "model_fields", {}):
            return False
        model = model.model_fields[part].annotation
    return True


def test_every_weights_spec_hint_names_a_real_option(host, package_sources):
    import importlib
    import re

    from vqtouch.plugins.cli.app import build_parser

    specs = {}  # id -> (where, spec): a spec imported by another module is the same object, counted once
    for path in package_sources:
        module = importlib.import_module(_module_name(path))
        for name, value in vars(module).items():
            if isinstance(value, WeightsSpec):
                specs.setdefault(id(value), (f"{module.__name__}.{name}", value))
    written = sum(path.read_text().count("WeightsSpec(") for path in package_sources)
    assert len(specs) == written, "a WeightsSpec is not a module attribute, so this test cannot check its hint"
    assert {spec.env_var for _, spec in specs.values()} >= {
        "VQTOUCH_CLIP_CKPT",
        "VQTOUCH_LPIPS_BACKBONE",
        "VQTOUCH_LPIPS_HEADS",
    }

    cli_options = _cli_options(build_parser(host))
    for name, spec in specs.values():
        hint = spec.config_hint
        unknown_flags = set(re.findall(r"--[a-z][a-z0-9-]*", hint)) - cli_options
        assert not unknown_flags, f"{name}: hint {hint!r} names CLI flags that do not exist: {sorted(unknown_flags)}"
        set_paths = re.findall(r"--set ([A-Za-z0-9_.]+)=", hint)
        for set_path in set_paths:
            assert _is_config_path(host, set_path.split(".")), f"{name}: hint {hint!r}: {set_path} is no config option"
        assert set_paths or spec.env_var in hint, f"{name}: hint {hint!r} names neither a --set path nor {spec.env_var}"

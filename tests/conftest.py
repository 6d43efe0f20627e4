"""Shared fixtures.  The suite is hermetic: third-party plugin autoload is off unless a
test turns it on explicitly, and progress bars are off."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

os.environ["VQTOUCH_DISABLE_PLUGIN_AUTOLOAD"] = "1"
os.environ["VQTOUCH_NO_PROGRESS"] = "1"
# The load-aware thread default would print a note (and change timings) whenever the machine running
# the suite is busy; tests/test_threads.py turns it back on.
os.environ["VQTOUCH_THREADS"] = "0"
# Reader header caches go to a throwaway folder, never the user's ~/.cache.
os.environ["XDG_CACHE_HOME"] = tempfile.mkdtemp(prefix="vqtouch-test-cache-")
for variable in (
    "VQTOUCH_BLOCK_PLUGINS",
    "VQTOUCH_PLUGINS",
    "VQTOUCH_CLIP_CKPT",
    "VQTOUCH_WEIGHTS_DIR",
    "VQTOUCH_LPIPS_VGG",
    "VQTOUCH_LPIPS_BACKBONE",
    "VQTOUCH_FID_INCEPTION",
):
    os.environ.pop(variable, None)

import torch  # noqa: E402

from vqtouch.core import load_plugins  # noqa: E402
from vqtouch.plugins.cli.app import main  # noqa: E402

TESTS = Path(__file__).resolve().parent
REPO = TESTS.parent


def _register_helper_module(name: str) -> None:
    """Make ``tests/<name>.py`` importable as ``import <name>``: test modules cannot import each
    other under --import-mode=importlib, and conftest is loaded before any of them."""
    spec = importlib.util.spec_from_file_location(name, TESTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)


_register_helper_module("dataset_fixtures")
_register_helper_module("cli_checks")
_register_helper_module("generator_runs")
_register_helper_module("metric_weights")
_register_helper_module("derived_condition_plugin")


@pytest.fixture(autouse=True)
def _seeded():
    torch.manual_seed(0)


@pytest.fixture(scope="session")
def host():
    """Built-in plugins only."""
    return load_plugins(autoload=False)


@pytest.fixture(scope="session")
def example_plugin_site(tmp_path_factory) -> Path:
    """The example third-party plugin, pip-installed (with its entry points) into a folder."""
    target = tmp_path_factory.mktemp("example_site")
    build_dir = tmp_path_factory.mktemp("example_build")
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "--quiet",
            "--no-deps",
            "--no-build-isolation",
            "--no-index",
            "--target",
            str(target),
            str(TESTS / "example_plugin"),
        ],
        check=True,
        cwd=build_dir,
        capture_output=True,
        text=True,
    )
    assert list(target.glob("vqtouch_example_plugin-*.dist-info"))
    return target


@pytest.fixture
def make_plugin():
    """Make an in-memory plugin module from hook functions: ``make_plugin("name", hook_fn, ...)``."""
    import types

    def make(name: str, *hooks):
        module = types.ModuleType(name)
        for hook in hooks:
            setattr(module, hook.__name__, hook)
        return module

    return make


@pytest.fixture
def built_kinds(monkeypatch) -> list[str]:
    """The registry kind of every component any PluginHost builds during the test, in order."""
    from vqtouch.core import PluginHost

    kinds: list[str] = []
    original = PluginHost.build

    def recording_build(self, kind, *args, **kwargs):
        kinds.append(kind)
        return original(self, kind, *args, **kwargs)

    monkeypatch.setattr(PluginHost, "build", recording_build)
    return kinds


@pytest.fixture
def third_party_conditioner(make_plugin):
    """An in-memory plugin module registering conditioner ``x`` (class ``plugin.Extra``)."""
    from typing import Literal

    from vqtouch.core import Conditioner, PluginConfig, hookimpl

    class ExtraConfig(PluginConfig):
        """Options of a third-party conditioner."""

        name: Literal["x"] = "x"

    class Extra(Conditioner):
        sample_key = "label"

        def encode(self, condition):
            return self.null_tokens_ND.expand(len(condition), -1, -1)

    @hookimpl
    def vqtouch_register_conditioners(register):
        register("x", lambda config, context: Extra(context.cond_dim, 1), ExtraConfig)

    plugin = make_plugin("pkg_plugin", vqtouch_register_conditioners)
    plugin.Extra = Extra
    return plugin


@pytest.fixture
def run_cli():
    """Run ``python -m vqtouch.plugins.cli ARGS`` in a subprocess (real entry-point discovery)."""
    return _run_cli


def _run_cli(
    *args: str, env_extra: dict[str, str] | None = None, cwd: Path | None = None, python_path: Path | None = None
) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    env.update(env_extra or {})
    if python_path is not None:
        env["PYTHONPATH"] = str(python_path) + os.pathsep + env.get("PYTHONPATH", "")
    return subprocess.run(
        [sys.executable, "-m", "vqtouch.plugins.cli", *args],
        capture_output=True,
        text=True,
        env=env,
        cwd=cwd or REPO,
        timeout=300,
    )


PACKAGE_FOLDERS = ("core", "plugins", "conditioners", "sensors")


@pytest.fixture(scope="session")
def package_sources() -> list[Path]:
    """Every .py file of the installable packages."""
    return [path for folder in PACKAGE_FOLDERS for path in sorted((REPO / folder).rglob("*.py"))]


def pytest_collection_modifyitems(config, items):
    """Skip `gpu` tests without CUDA, saying why (every other test runs on every `make test`)."""
    for item in items:
        if "gpu" in item.keywords and not torch.cuda.is_available():
            item.add_marker(pytest.mark.skip(reason="gpu: no CUDA device on this machine"))


@pytest.fixture(scope="module")
def tiny_label_run(tmp_path_factory):
    """A tiny trained label-to-touch run (``generator_runs.train_args``: 32 px, a few steps): a real
    tokenizer, generator and label conditioner for the sampling tests."""
    from generator_runs import train_args

    out = tmp_path_factory.mktemp("label_run") / "run"
    assert main(train_args(out)) == 0
    return out


@pytest.fixture(scope="module")
def family_tokenizer_run(tmp_path_factory):
    """A tiny tokenizer run (32 px): the family tokenizer of the adaptation experiments' tests."""
    from generator_runs import tiny_tokenizer_args

    out = tmp_path_factory.mktemp("family") / "tok"
    assert main(tiny_tokenizer_args(out)) == 0
    return out


@pytest.fixture(scope="module")
def family_clusters(family_tokenizer_run, tmp_path_factory):
    """Two families (GelSight with a variant, DIGIT) clustered with :func:`family_tokenizer_run`."""
    from generator_runs import cluster_args

    out = tmp_path_factory.mktemp("families")
    variant = json.dumps({"name": "gelsight", "variant": {"seed": 1, "colour_gain": [1.05, 0.95, 0.95]}})
    assert main(cluster_args(family_tokenizer_run, out, ["gelsight", variant, "digit"])) == 0
    return out


@pytest.fixture
def tokenizer_trainer_calls(monkeypatch):
    """What every tokenizer trainer of the experiment received: its stage and its images."""
    from vqtouch.plugins.training import trainer as training

    calls = []

    class Recording(training.Trainer):
        def __init__(self, task, dataset, config, **kwargs):
            calls.append({"stage": kwargs.get("stage"), "images": dataset.images.clone(), "steps": config.steps})
            super().__init__(task, dataset, config, **kwargs)

    monkeypatch.setattr(training, "Trainer", Recording)
    return calls

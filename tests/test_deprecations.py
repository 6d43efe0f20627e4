"""The API keeps its promises: every 0.1.0 name either works with one deprecation warning naming
the new name, or is refused in one line naming what replaced it; never a late traceback."""

from __future__ import annotations

import re
import warnings
from pathlib import Path
from typing import Literal

import pytest
import torch
from safetensors import safe_open
from safetensors.torch import save_file

from vqtouch.core import (
    Assembly,
    BuildContext,
    Conditioner,
    ConfigError,
    PluginError,
    VqtouchDeprecationWarning,
    hookimpl,
    load,
    load_plugins,
    resolve_config,
    save,
)
from vqtouch.core import deprecations
from vqtouch.core.config import migrate_config

REPO = Path(__file__).resolve().parents[1]


def _deprecations(record) -> list[str]:
    return [str(w.message) for w in record if issubclass(w.category, VqtouchDeprecationWarning)]


@pytest.mark.parametrize(
    "override, new_path, expected",
    [
        ('conditioner={"name": "label"}', "generator.conditioners", "label"),
        ("tokenizer.encoder.name=vqgan", "tokenizer.autoencoder", "vqgan"),
        ("clusterer.name=kmeans", "cluster.clusterer", "kmeans"),
        ('generator={"name": "vq_diffusion", "depth": 3}', "generator.model", "vq_diffusion"),
    ],
)
def test_a_0_1_0_config_key_still_works_with_one_warning_naming_the_new_key(host, override, new_path, expected):
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        config = resolve_config("tour", overrides=[override], host=host)
    value = config.slot(new_path)
    names = [item.name for item in value] if isinstance(value, list) else [value.name]
    assert names == [expected]
    messages = _deprecations(record)
    assert len(messages) == 1 and f"renamed to {new_path!r}" in messages[0] and "\n" not in messages[0]


def test_an_old_generator_block_keeps_its_options(host):
    with pytest.warns(VqtouchDeprecationWarning, match="generator.model"):
        config = resolve_config("tour", overrides=['generator={"name": "vq_diffusion", "depth": 3}'], host=host)
    assert config.generator.model.depth == 3
    # The rest of the generator section (the scene's conditioners) is untouched.
    assert len(config.generator.conditioners) == 4


def test_the_split_train_section_is_refused_in_one_line_naming_its_new_homes(host):
    with pytest.raises(ConfigError) as error:
        resolve_config("tour", overrides=["train.steps=200"], host=host)
    message = str(error.value)
    assert "tokenizer.train" in message and "generator.train" in message and "\n" not in message


def test_the_removed_evaluate_stage_is_refused_naming_the_command_that_replaced_it(host):
    with pytest.raises(ConfigError, match=r"stage 'evaluate' .* removed .*vqtouch evaluate"):
        resolve_config("tour", overrides=['stages=["tokenizer", "evaluate"]'], host=host)


def test_todays_scenes_need_no_migration(host):
    with warnings.catch_warnings():
        warnings.simplefilter("error", VqtouchDeprecationWarning)
        for name, scene in host.scenes.items():
            assert migrate_config(scene.config, host.stages) == scene.config, name
            resolve_config(name, host=host)


def test_a_0_1_0_conditioner_declaring_modality_reads_that_key():
    with pytest.warns(VqtouchDeprecationWarning, match=r"OldStyle\.modality' was renamed to 'OldStyle\.sample_key'"):

        class OldStyle(Conditioner):
            modality = "text"

            def encode(self, condition):
                return self.null_tokens_ND.expand(len(condition), -1, -1)

    assert OldStyle.sample_key == "text"
    assert OldStyle(8, 1).condition_of({"text": ["a"], "label": torch.tensor([0])}) == ["a"]


def test_old_python_names_still_work_with_a_warning(host):
    import vqtouch.core as core

    with pytest.warns(VqtouchDeprecationWarning, match="'vqtouch.core.Autoencoder'"):
        assert core.Encoder is core.Autoencoder
    config = resolve_config("label-to-touch", host=host)
    with pytest.warns(VqtouchDeprecationWarning, match=r"Assembly\(config, host\)\.build_slots"):
        built = core.build_components(config, host, slots=["generator.conditioners"])
    expected = Assembly(config, host).build_slots(["generator.conditioners"])
    assert [type(c) for c in built["generator.conditioners"]] == [type(c) for c in expected["generator.conditioners"]]


def _label_checkpoint(host, path: Path) -> Path:
    return save(
        host.build("conditioner", {"name": "label", "num_tokens": 2}, BuildContext(num_classes=3, cond_dim=8)),
        path,
        step=1,
        host=host,
    )


def test_load_without_host_is_refused_in_one_line_saying_what_to_pass(host, tmp_path):
    path = _label_checkpoint(host, tmp_path / "label.safetensors")
    with pytest.raises(TypeError, match=r"load\(\) needs host= since vqtouch 0.2.0 .*load_plugins\(\)") as error:
        load(path)
    assert "\n" not in str(error.value)


def test_a_checkpoint_under_an_old_kind_name_loads_under_the_new_one(host, tmp_path):
    encoder = host.build(
        "autoencoder",
        {
            "name": "vqgan",
            "channels": 8,
            "channel_multipliers": [1, 1],
            "z_channels": 4,
            "embed_dim": 4,
            "norm_groups": 4,
        },
        BuildContext(),
    )
    path = save(encoder, tmp_path / "enc.safetensors", step=2, host=host)
    with safe_open(str(path), "pt") as handle:
        metadata = handle.metadata()
        tensors = {key: handle.get_tensor(key) for key in handle.keys()}
    assert metadata["vqtouch.component"] == "autoencoder"
    old = tmp_path / "old.safetensors"
    save_file(tensors, str(old), metadata={**metadata, "vqtouch.component": "encoder"})
    with pytest.warns(VqtouchDeprecationWarning, match="component kind 'encoder' was renamed to 'autoencoder'"):
        loaded = load(old, host=host)
    assert all(torch.equal(a, b) for a, b in zip(loaded.state_dict().values(), encoder.state_dict().values()))


def test_a_plugin_on_the_old_registration_hook_still_registers(make_plugin):
    from vqtouch.plugins.tokenizer.autoencoder import VqganConfig, build_autoencoder

    class OldConfig(VqganConfig):
        name: Literal["old_vqgan"] = "old_vqgan"

    @hookimpl
    def vqtouch_register_encoders(register):
        register("old_vqgan", build_autoencoder, OldConfig)

    with pytest.warns(VqtouchDeprecationWarning, match="vqtouch_register_autoencoders"):
        host = load_plugins(autoload=False, extra=[make_plugin("oldpkg", vqtouch_register_encoders)])
    assert "old_vqgan" in host.registry("autoencoder")


def test_a_plugin_on_a_removed_hook_is_refused_in_one_line_naming_it(make_plugin):
    @hookimpl
    def vqtouch_run_stage(stage, config, host, run):
        return None

    with pytest.raises(PluginError) as error:
        load_plugins(autoload=False, extra=[make_plugin("stagepkg", vqtouch_run_stage)])
    message = str(error.value)
    assert "'stagepkg'" in message and "vqtouch_register_stages" in message and "\n" not in message


def test_a_validate_hook_that_crashes_is_reported_in_one_line_naming_its_plugin(make_plugin):
    @hookimpl
    def vqtouch_validate_experiment(config):
        return config.data.image_size[1]  # a plugin bug: image_size is an int here

    host = load_plugins(autoload=False, extra=[make_plugin("buggy", vqtouch_validate_experiment)])
    with pytest.raises(PluginError, match=r"plugin 'buggy' failed in vqtouch_validate_experiment: TypeError"):
        resolve_config("label-to-touch", host=host)


def test_the_cli_prints_a_rename_as_one_warning_line_and_a_removed_key_as_one_error_line(run_cli):
    renamed = run_cli("config", "show", "label-to-touch", "--set", 'conditioner={"name": "label"}')
    assert renamed.returncode == 0, renamed.stderr
    lines = [line for line in renamed.stderr.splitlines() if "renamed" in line]
    assert lines == [
        "vqtouch: warning: config key 'conditioner' was renamed to 'generator.conditioners' in vqtouch "
        "0.2.0; use 'generator.conditioners' ('conditioner' stops working in 0.3.0)"
    ]
    removed = run_cli("config", "show", "label-to-touch", "--set", "train.steps=3")
    assert removed.returncode == 2
    assert removed.stderr.count("\n") == 1 and "tokenizer.train" in removed.stderr


def test_every_rename_is_in_the_changelog_and_the_version_says_so():
    changelog = (REPO / "CHANGELOG.md").read_text(encoding="utf-8")
    section = changelog.split(f"## {deprecations.RENAMED_IN}", 1)[1].split("\n## ", 1)[0]
    names = (
        [r.old for r in deprecations.CONFIG_RENAMES]
        + list(deprecations.CONFIG_REMOVED)
        + list(deprecations.STAGES_REMOVED)
        + list(deprecations.KIND_RENAMES)
        + list(deprecations.HOOK_RENAMES)
        + list(deprecations.HOOKS_REMOVED)
        + ["modality", "Encoder", "build_components", "load"]
    )
    # The old name is the first quoted name of a table row or a bullet (the "0.1.0" side).
    first_spans = [
        re.search(r"`([^`]+)`", line).group(1)
        for line in section.splitlines()
        if line.startswith(("| ", "- ")) and "`" in line
    ]
    missing = [
        name
        for name in names
        if not any(span == name or span.endswith("." + name) or span.startswith(name + "(") for span in first_spans)
    ]
    assert not missing, f"CHANGELOG {deprecations.RENAMED_IN} does not describe {missing}"
    version = re.search(r'^version = "([^"]+)"', (REPO / "pyproject.toml").read_text(), re.M).group(1)
    assert version == deprecations.RENAMED_IN


@pytest.mark.parametrize("old", sorted(deprecations.MOVED_MODULES))
def test_a_module_that_left_the_core_still_imports_with_one_warning_naming_its_new_home(old):
    import importlib
    import sys

    sys.modules.pop(old, None)
    with pytest.warns(VqtouchDeprecationWarning, match=re.escape(deprecations.MOVED_MODULES[old][0])):
        module = importlib.import_module(old)
    homes = [importlib.import_module(home) for home in deprecations.MOVED_MODULES[old]]
    # What the new home exports (its __all__), else what it defines itself.
    own = [name for name, value in vars(homes[0]).items() if getattr(value, "__module__", None) == homes[0].__name__]
    names = getattr(homes[0], "__all__", None) or own
    assert names, f"{old}'s new home defines nothing"
    for name in names:
        assert getattr(module, name) is getattr(homes[0], name)
    with pytest.raises(AttributeError, match="has no attribute 'not_a_name'"):
        module.not_a_name  # noqa: B018


@pytest.mark.parametrize(
    ("name", "home"),
    [("TrainConfig", "vqtouch.plugins.training.settings"), ("RunDir", "vqtouch.plugins.runtime.run_dir"),
     ("run_stage", "vqtouch.plugins.runtime.execution"), ("seed_everything", "vqtouch.plugins.utils.seeding"),
     ("MetricSet", "vqtouch.plugins.evaluation.metric_set")],
)  # fmt: skip
def test_a_name_that_left_the_core_still_imports_from_vqtouch_core_with_a_warning(name, home):
    import importlib

    import vqtouch.core

    with pytest.warns(VqtouchDeprecationWarning, match=re.escape(f"{home}.{name}")):
        value = getattr(vqtouch.core, name)
    assert value is getattr(importlib.import_module(home), name)


def test_the_package_imports_nothing_from_the_old_core_paths():
    """Every built-in, test and bench script imports a moved module from its new home (a patch of
    the old path would patch a stand-in)."""
    old = "|".join(re.escape(path) for path in deprecations.MOVED_MODULES)
    moved = "|".join(path.rsplit(".", 1)[1] for path in deprecations.MOVED_MODULES)
    pattern = re.compile(rf"^\s*(from ({old})\b|import ({old})\b|from vqtouch\.core import ({moved})\b)", re.M)
    offenders = [
        str(path.relative_to(REPO))
        for folder in ("core", "plugins", "conditioners", "sensors", "tests", "bench")
        for path in (REPO / folder).rglob("*.py")
        if pattern.search(path.read_text(encoding="utf-8"))
    ]
    assert not offenders, f"import from the old core paths: {offenders}"

import inspect
import re
from pathlib import Path
from typing import Literal

import pytest
import torch
from pydantic import Field

from vqtouch.core import (
    Autoencoder,
    Clusterer,
    Conditioner,
    ConfigError,
    Discriminator,
    Generator,
    PluginConfig,
    PluginError,
    Quantizer,
    Sampler,
    Section,
    SensorFamily,
    Slot,
    StageUnavailable,
    TactileDataset,
    UnknownPluginError,
    hookimpl,
    hookspecs,
    load_plugins,
    resolve_config,
)
from vqtouch.core.plugin_manager import REGISTRY_KINDS

TESTS = Path(__file__).resolve().parent

BUILTIN_PLUGINS = {
    "label",
    "tactile",
    "clip",
    "metrics",
    "scenes",
    "tokenizer-stages",
    "data-stages",
    "generator",
    "adaptation",
}
BUILTIN_STAGES = {"render", "tokenizer", "reconstruct", "cluster", "adapt", "generator", "fewshot", "pretrained"}


def test_builtins_load_through_entry_points_with_autoload_off(host):
    assert BUILTIN_PLUGINS <= set(host.sources)
    for name in BUILTIN_PLUGINS:
        assert host.sources[name].distribution == "vqtouch"
    conditioners = host.registry("conditioner").names()
    assert conditioners == sorted(conditioners)
    assert {"label", "tactile", "tactile_codes", "visual", "visual_cnn", "clip", "text", "text_scratch"} <= set(
        conditioners
    )
    assert all(entry.source.distribution == "vqtouch" for entry in host.registry("conditioner"))
    assert {"psnr", "ssim", "fd_effnetlite0"} <= set(host.registry("metric").names())
    assert {"few-shot", "zero-shot", "cross-sensor", "vision-to-touch", "label-to-touch", "touch-to-touch"} <= set(
        host.scenes
    )
    assert set(host.stages) == BUILTIN_STAGES
    for stage in host.stages.values():
        assert stage.source.distribution == "vqtouch" and stage.description


def test_there_is_no_process_wide_host(make_plugin):
    """Each load_plugins() is its own host: what one loads, another does not see."""
    import vqtouch.core as core
    from vqtouch.core import config as config_module, plugin_manager

    for module in (core, plugin_manager, config_module):
        for name in ("default_host", "current_host", "reset_default_host"):
            assert not hasattr(module, name), f"{module.__name__}.{name}"

    @hookimpl
    def vqtouch_register_conditioners(register):
        register(
            "extra_cond",
            lambda config, context: ExtraConditioner(context.cond_dim, 1),
            ExtraConfig,
            description="extra",
        )

    with_extra = load_plugins(autoload=False, extra=[make_plugin("my_extra", vqtouch_register_conditioners)])
    plain = load_plugins(autoload=False)
    assert "extra_cond" in with_extra.registry("conditioner") and "extra_cond" not in plain.registry("conditioner")
    overrides = ['generator.conditioners=[{"name": "extra_cond"}]']
    chosen = resolve_config("label-to-touch", overrides=overrides, host=with_extra).generator.conditioners
    assert [item.name for item in chosen] == ["extra_cond"]
    with pytest.raises(ConfigError, match="unknown conditioner 'extra_cond'"):
        resolve_config("label-to-touch", overrides=overrides, host=plain)


def test_every_registry_kind_has_a_hookspec():
    for kind in REGISTRY_KINDS:
        assert hasattr(hookspecs, kind.hook), kind


def test_block_removes_a_builtin():
    host = load_plugins(autoload=False, block=["clip"])
    assert "clip" not in host.registry("conditioner")
    assert "label" in host.registry("conditioner")


def test_block_from_environment(monkeypatch):
    full = load_plugins(autoload=False)
    monkeypatch.setenv("VQTOUCH_BLOCK_PLUGINS", "metrics, label")
    host = load_plugins(autoload=False)
    # psnr, ssim, ms_ssim and lpips came from "metrics": none is left, the other plugins' metrics are.
    from_metrics = {entry.name for entry in full.registry("metric") if entry.source.plugin == "metrics"}
    assert {"psnr", "ssim", "ms_ssim", "lpips"} <= from_metrics
    assert set(host.registry("metric").names()) == set(full.registry("metric").names()) - from_metrics
    assert "label" not in host.registry("conditioner") and "label" in full.registry("conditioner")


class ExtraConfig(PluginConfig):
    name: Literal["extra_cond"] = "extra_cond"


class ExtraConditioner(Conditioner):
    def encode(self, condition):
        return condition


def test_extra_module_registers_and_source_is_recorded(make_plugin):
    @hookimpl
    def vqtouch_register_conditioners(register):
        register(
            "extra_cond",
            lambda config, context: ExtraConditioner(context.cond_dim, 1),
            ExtraConfig,
            description="extra",
        )

    host = load_plugins(autoload=False, extra=[make_plugin("my_extra", vqtouch_register_conditioners)])
    entry = host.registry("conditioner").get("extra_cond")
    assert entry.source.plugin == "my_extra" and entry.source.distribution is None
    assert isinstance(host.build("conditioner", "extra_cond"), ExtraConditioner)


def test_extra_module_by_dotted_name_from_environment(monkeypatch):
    monkeypatch.setenv("VQTOUCH_PLUGINS", "vqtouch.plugins.evaluation.metrics_plugin")
    host = load_plugins(autoload=False, block=["metrics"])
    assert {"psnr", "ssim"} <= set(host.registry("metric").names())
    assert host.registry("metric").get("psnr").source.plugin == "vqtouch.plugins.evaluation.metrics_plugin"


def test_misspelled_hook_fails_loudly(make_plugin):
    @hookimpl
    def vqtouch_register_conditioner(register):  # missing trailing "s"
        pass

    with pytest.raises(PluginError, match="vqtouch_register_conditioner"):
        load_plugins(autoload=False, extra=[make_plugin("typo", vqtouch_register_conditioner)])


def test_exception_in_registration_hook_names_plugin_and_block_hint(make_plugin):
    @hookimpl
    def vqtouch_register_metrics(register):
        raise RuntimeError("boom")

    with pytest.raises(
        PluginError, match=r"plugin 'broken'.*vqtouch_register_metrics.*boom.*VQTOUCH_BLOCK_PLUGINS=broken"
    ):
        load_plugins(autoload=False, extra=[make_plugin("broken", vqtouch_register_metrics)])


def test_duplicate_registration_across_plugins_names_both(make_plugin):
    @hookimpl
    def vqtouch_register_conditioners(register):
        class LabelConfig(PluginConfig):
            name: Literal["label"] = "label"

        register("label", lambda c, x: None, LabelConfig)

    with pytest.raises(
        PluginError, match=r"duplicate conditioner name 'label'.*plugin 'label' \(vqtouch .*\).*plugin 'dup'"
    ):
        load_plugins(autoload=False, extra=[make_plugin("dup", vqtouch_register_conditioners)])


def test_factory_returning_wrong_type_is_rejected(make_plugin):
    @hookimpl
    def vqtouch_register_conditioners(register):
        register("extra_cond", lambda config, context: object(), ExtraConfig)

    host = load_plugins(autoload=False, extra=[make_plugin("wrong", vqtouch_register_conditioners)])
    with pytest.raises(PluginError, match="not a vqtouch.core.Conditioner"):
        host.build("conditioner", "extra_cond")


def test_bad_import_in_extra_module_is_reported():
    with pytest.raises(PluginError, match="error loading plugin module 'no_such_module_xyz'"):
        load_plugins(autoload=False, extra=["no_such_module_xyz"])


def test_every_hookspec_is_exercised_by_some_test():
    """datasette-style meta-test: each hook in hookspecs appears in the tests."""
    test_sources = "".join(path.read_text() for path in TESTS.rglob("*.py"))
    hooks = [name for name, _ in inspect.getmembers(hookspecs, inspect.isfunction) if name.startswith("vqtouch_")]
    assert len(hooks) >= 12
    untested = [hook for hook in hooks if hook not in test_sources]
    assert not untested, f"hooks without a test implementation: {untested}"


class _Autoencoder(Autoencoder):
    def encode(self, images_BCHW):
        return images_BCHW

    def decode(self, latents_BDhw):
        return latents_BDhw


class _Quantizer(Quantizer):
    def forward(self, latents_BDhw):
        return latents_BDhw

    def lookup(self, codes_Bhw):
        return codes_Bhw


class _Clusterer(Clusterer):
    def fit(self, features_NF):
        return torch.zeros(len(features_NF), dtype=torch.long)

    def predict(self, features_NF):
        return torch.zeros(len(features_NF), dtype=torch.long)


class _Dataset(TactileDataset):
    def __len__(self):
        return 0

    def __getitem__(self, index):
        raise IndexError(index)


class _Sensor(SensorFamily):
    def render(self, height_mm_BHW, generator=None):
        return height_mm_BHW[:, None].expand(-1, 3, -1, -1)


class _Generator(Generator):
    def training_loss(self, codes_BHW, condition, generator=None):
        return torch.zeros(()), {}

    def sample(self, condition, sampler, *, steps, null=None, guidance=1.0, truncation=1.0, generators=None):
        return torch.zeros(len(condition.tokens_BND), 1, 1, dtype=torch.long)


class _Sampler(Sampler):
    def sample(self, denoise, schedule, *, length, steps, generators):
        return torch.zeros(len(generators), length, dtype=torch.long)


class _Discriminator(Discriminator):
    def forward(self, images_BCHW):
        return images_BCHW.mean(dim=(1, 2, 3))


# One minimal implementation per registration hook, registered through that hook by name.
MINIMAL = {
    "vqtouch_register_autoencoders": ("autoencoder", _Autoencoder),
    "vqtouch_register_quantizers": ("quantizer", _Quantizer),
    "vqtouch_register_clusterers": ("clusterer", _Clusterer),
    "vqtouch_register_datasets": ("dataset", _Dataset),
    "vqtouch_register_sensor_families": ("sensor_family", _Sensor),
    "vqtouch_register_generators": ("generator", _Generator),
    "vqtouch_register_samplers": ("sampler", _Sampler),
    "vqtouch_register_discriminators": ("discriminator", _Discriminator),
}


@pytest.mark.parametrize("hook_name", sorted(MINIMAL))
def test_each_registration_hook_registers_a_buildable_component(hook_name, make_plugin):
    kind, cls = MINIMAL[hook_name]

    class MiniConfig(PluginConfig):
        name: Literal["mini"] = "mini"

    def register_hook(register):
        register("mini", lambda config, context: cls(), MiniConfig, description="minimal")

    register_hook.__name__ = hook_name
    plugin = make_plugin("mini_plugin", hookimpl(register_hook))
    host = load_plugins(autoload=False, extra=[plugin])
    component = host.build(kind, {"name": "mini"})
    assert isinstance(component, cls)
    assert component.vqtouch_spec.kind == kind
    assert host.registry(kind).get("mini").source.plugin == "mini_plugin"


def test_scene_hook_registers_scene_and_rejects_duplicates(make_plugin):
    @hookimpl
    def vqtouch_register_scenes(register):
        register("my-scene", {"stages": ["render"], "metrics": [{"name": "psnr"}]}, description="mine")

    host = load_plugins(autoload=False, extra=[make_plugin("scenes_extra", vqtouch_register_scenes)])
    assert host.scene("my-scene").description == "mine"
    config = resolve_config("my-scene", host=host)
    assert config.stages == ["render"] and config.metrics[0].name == "psnr"

    @hookimpl
    def vqtouch_register_scenes(register):  # noqa: F811 - a second plugin reusing a built-in name
        register("few-shot", {}, description="again")

    with pytest.raises(PluginError, match="duplicate scene 'few-shot'"):
        load_plugins(autoload=False, extra=[make_plugin("dup_scene", vqtouch_register_scenes)])


def test_trace_variable_traces_hook_calls(monkeypatch, capfd):
    monkeypatch.setenv("VQTOUCH_TRACE_PLUGINS", "1")
    host = load_plugins(autoload=False)
    host.pm.hook.vqtouch_validate_experiment(config=None)
    assert "vqtouch_validate_experiment" in capfd.readouterr().err


def test_describe_rows_have_versions(host):
    rows = host.describe()
    assert {row["kind"] for row in rows} >= {"conditioner", "metric", "scene", "stage", "autoencoder"}
    assert {row["name"] for row in rows if row["kind"] == "stage"} == BUILTIN_STAGES
    assert all(row["version"] for row in rows if row["package"] == "vqtouch")


# -- inputs and demo caps of a registration -----------------------------------------------------------


class _RenderedDataset(_Dataset):
    def __init__(self, sensor):
        self.sensor = sensor


class RenderedConfig(PluginConfig):
    """A dataset rendered by the experiment's sensor."""

    name: Literal["rendered"] = "rendered"
    num_samples: int = Field(8, ge=1, description="Samples.")


def test_declared_inputs_are_supplied_by_the_caller(make_plugin, host):
    @hookimpl
    def vqtouch_register_datasets(register):
        register(
            "rendered",
            lambda config, context, sensor: _RenderedDataset(sensor),
            RenderedConfig,
            description="rendered",
            inputs=("sensor",),
            demo={"num_samples": 2},
        )

    with_plugin = load_plugins(autoload=False, extra=[make_plugin("rendered_plugin", vqtouch_register_datasets)])
    entry = with_plugin.registry("dataset").get("rendered")
    assert entry.inputs == ("sensor",) and entry.demo == {"num_samples": 2}
    with pytest.raises(
        ConfigError,
        match=r"dataset 'rendered' needs sensor: build it through the experiment's "
        r"Assembly .* or pass sensor=\.\.\.",
    ):
        with_plugin.build("dataset", "rendered")
    sensor = with_plugin.build("sensor_family", "gelsight")
    assert with_plugin.build("dataset", "rendered", sensor=sensor).sensor is sensor
    with pytest.raises(PluginError, match="takes no input 'camera'"):
        with_plugin.build("dataset", "rendered", sensor=sensor, camera=sensor)
    # The built-in procedural dataset renders with the sensor it is given (it has no sensor option).
    assert "sensor" not in host.registry("dataset").get("procedural").config_model.model_fields
    digit = host.build("sensor_family", "digit")
    procedural = host.build("dataset", {"name": "procedural", "num_samples": 2}, sensor=digit)
    assert procedural.sensor is digit and procedural[0]["sensor"] == (digit.sensor_id or "digit")


# -- stages are a registry kind owned by plugins ----------------------------------------------------


class GallerySection(Section):
    """Options of the test's ``gallery`` stage."""

    columns: int = Field(3, ge=1, description="Pictures per row.")
    backdrop: Slot("sensor_family") | None = Field(None, description="A second sensor to compare with.")


def _run_gallery(job):
    if job.section.columns > 10:
        raise StageUnavailable("too many columns")
    return {
        "columns": job.section.columns,
        "sensor": job.config.sensor.name,
        "renders": isinstance(job.assembly.sensor(), SensorFamily),
    }


def _stage_plugin(make_plugin, name="gallery", **options):
    options = {
        "section": GallerySection,
        "needs": ("sensor",),
        "uses": ("gallery.backdrop",),
        "description": "A test stage.",
        **options,
    }

    @hookimpl
    def vqtouch_register_stages(register):
        register(name, _run_gallery, **options)

    return make_plugin(f"stage_{name}", vqtouch_register_stages)


def test_stage_registers_its_section_and_slots_and_runs(make_plugin, tmp_path):
    from vqtouch.core import Assembly
    from vqtouch.plugins.runtime.execution import run_stage
    from vqtouch.plugins.runtime.run_dir import RunDir

    host = load_plugins(autoload=False, extra=[_stage_plugin(make_plugin, demo={"columns": 2})])
    stage = host.stage("gallery")
    assert stage.needs == ("sensor",) and stage.slots == ("sensor", "gallery.backdrop") and stage.demo == {"columns": 2}
    assert stage.source.plugin == "stage_gallery"
    assert host.slots["gallery.backdrop"].kind == "sensor_family"
    assert host.experiment_model.model_fields["gallery"].description == "A test stage."
    config = resolve_config(overrides=['stages=["gallery"]', "gallery.columns=4", "sensor.name=digit"], host=host)
    assert config.gallery.columns == 4
    with pytest.raises(
        ConfigError, match=r"gallery: unknown option 'colums'; allowed: backdrop, columns; did you mean 'columns'"
    ):
        resolve_config(overrides=["gallery.colums=4"], host=host)

    def run(overrides, folder):
        config = resolve_config(overrides=['stages=["gallery"]', *overrides], host=host)
        return run_stage("gallery", Assembly(config, host), RunDir.create(config, host=host, path=tmp_path / folder))

    outcome = run(["gallery.columns=4", "sensor.name=digit"], "ran")
    assert outcome.status == "ran" and outcome.result == {"columns": 4, "sensor": "digit", "renders": True}
    outcome = run([], "no-sensor")
    assert outcome.status == "unavailable" and "needs sensor" in outcome.reason
    outcome = run(["gallery.columns=11", "sensor.name=digit"], "wide")
    assert outcome.status == "unavailable" and outcome.reason == "too many columns"
    # A host without the plugin knows neither the stage nor its section.
    plain = load_plugins(autoload=False)
    assert "gallery" not in plain.stages and "gallery" not in plain.experiment_model.model_fields
    with pytest.raises(UnknownPluginError, match="unknown stage 'gallery'; available: adapt, cluster"):
        plain.stage("gallery")
    with pytest.raises(ConfigError, match="unknown stage 'gallery'"):
        resolve_config(overrides=['stages=["gallery"]'], host=plain)


@pytest.mark.parametrize(
    "options, message",
    [
        ({"name": "tokenizer"}, r"duplicate stage 'tokenizer'.*plugin 'tokenizer-stages'.*plugin 'stage_tokenizer'"),
        ({"name": "seed"}, "section would replace core's 'seed' field"),
        ({"needs": ("gallery.nothing",)}, "declares slot 'gallery.nothing', which the experiment config does not have"),
        ({"section": dict}, "section must subclass vqtouch.core.Section"),
    ],
    ids=["duplicate", "core-field", "unknown-slot", "bad-section"],
)
def test_bad_stage_registrations_fail_when_plugins_load(make_plugin, options, message):
    with pytest.raises(PluginError, match=message):
        load_plugins(autoload=False, extra=[_stage_plugin(make_plugin, **options)])


def test_removed_hooks_fail_loudly(make_plugin):
    """vqtouch_run_stage is gone: a plugin still using it fails to load (vqtouch_register_encoders still
    registers, with a deprecation warning: tests/test_deprecations.py)."""

    @hookimpl
    def vqtouch_run_stage(stage, config, run):
        return None

    with pytest.raises(PluginError, match="vqtouch_run_stage"):
        load_plugins(autoload=False, extra=[make_plugin("old_stage", vqtouch_run_stage)])


def test_a_stage_plugins_section_does_not_leak_into_runs_that_do_not_use_it(make_plugin, tmp_path):
    """A run records only the sections its stages use: a run made while a stage plugin is installed
    still opens after it is removed; a run that used the stage names the plugin that is missing."""
    import json

    from vqtouch.plugins.runtime.run_dir import RunDir

    with_gallery = load_plugins(autoload=False, extra=[_stage_plugin(make_plugin)])
    plain = load_plugins(autoload=False)
    other = resolve_config("reconstruction", host=with_gallery)
    other_run = RunDir.create(other, host=with_gallery, path=tmp_path / "other")
    recorded = json.loads((other_run.path / "config.json").read_text())
    assert "gallery" not in recorded and "tokenizer" in recorded
    other_run.close()
    assert RunDir.open(other_run.path).load_config(plain) == resolve_config("reconstruction", host=plain)

    used = resolve_config(overrides=['stages=["gallery"]', "sensor.name=digit", "gallery.columns=5"], host=with_gallery)
    used_run = RunDir.create(used, host=with_gallery, path=tmp_path / "used")
    used_run.close()
    assert RunDir.open(used_run.path).load_config(with_gallery).gallery.columns == 5
    with pytest.raises(ConfigError) as error:
        RunDir.open(used_run.path).load_config(plain)
    # An in-memory plugin has no distribution, so its plugin name stands for it.
    assert str(error.value).endswith(
        "its config section 'gallery' belongs to stage 'gallery' from stage_gallery "
        "(plugin 'stage_gallery'), which is not installed here; pip install stage_gallery"
    )
    assert "\n" not in str(error.value)


def test_check_plugin_covers_stages(make_plugin, host):
    from vqtouch.plugins.testing import check_plugin

    for name in host.stages:
        assert check_plugin(host, "stage", name).name == name
    good = load_plugins(autoload=False, extra=[_stage_plugin(make_plugin, demo={"columns": 2})])
    assert check_plugin(good, "stage", "gallery").section is GallerySection

    class Undocumented(GallerySection):
        """A section with an undocumented option."""

        width: int = 3

    cases = [
        ({"section": Undocumented}, "section Undocumented fields without description: ['width']"),
        ({"demo": {"colums": 2}}, "demo caps name options its section does not have: ['colums']"),
        ({"description": ""}, "no description"),
    ]
    for options, message in cases:
        bad = load_plugins(autoload=False, extra=[_stage_plugin(make_plugin, **options)])
        with pytest.raises(AssertionError, match=re.escape(message)):
            check_plugin(bad, "stage", "gallery")
    with pytest.raises(AssertionError, match="stage 'nope' is not registered"):
        check_plugin(host, "stage", "nope")

import inspect
from typing import Literal

import pytest

import torch

from vqtouch.core import (Clusterer, Conditioner, Discriminator, Encoder, Generator, PluginConfig, PluginError, Quantizer,
                          SensorFamily, TactileDataset, hookimpl, hookspecs, load_plugins)
from vqtouch.core.plugin_manager import REGISTRY_KINDS
from pathlib import Path

TESTS = Path(__file__).resolve().parent

BUILTIN_PLUGINS = {"label", "tactile", "clip", "metrics", "scenes"}


def test_builtins_load_through_entry_points_with_autoload_off(host):
    assert BUILTIN_PLUGINS <= set(host.sources)
    for name in BUILTIN_PLUGINS:
        assert host.sources[name].distribution == "vqtouch"
    assert host.registry("conditioner").names() == ["clip", "label", "tactile"]
    assert {"psnr", "ssim", "fd_effnetlite0"} <= set(host.registry("metric").names())
    assert {"few-shot", "zero-shot", "cross-sensor", "vision-to-touch", "label-to-touch",
            "touch-to-touch"} <= set(host.scenes)


def test_every_registry_kind_has_a_hookspec():
    for kind in REGISTRY_KINDS:
        assert hasattr(hookspecs, kind.hook), kind


def test_block_removes_a_builtin():
    host = load_plugins(autoload=False, block=["clip"])
    assert "clip" not in host.registry("conditioner")
    assert "label" in host.registry("conditioner")


def test_block_from_environment(monkeypatch):
    monkeypatch.setenv("VQTOUCH_BLOCK_PLUGINS", "metrics, label")
    host = load_plugins(autoload=False)
    assert host.registry("metric").names() == ["fd_effnetlite0"]  # psnr and ssim came from "metrics"
    assert "label" not in host.registry("conditioner")


class ExtraConfig(PluginConfig):
    name: Literal["extra_cond"] = "extra_cond"


class ExtraConditioner(Conditioner):
    def encode(self, condition):
        return condition


def test_extra_module_registers_and_source_is_recorded(make_plugin):
    @hookimpl
    def vqtouch_register_conditioners(register):
        register("extra_cond", lambda config, context: ExtraConditioner(context.cond_dim, 1), ExtraConfig,
                 description="extra")

    host = load_plugins(autoload=False, extra=[make_plugin("my_extra", vqtouch_register_conditioners)])
    entry = host.registry("conditioner").get("extra_cond")
    assert entry.source.plugin == "my_extra" and entry.source.distribution is None
    assert isinstance(host.build("conditioner", "extra_cond"), ExtraConditioner)


def test_extra_module_by_dotted_name_from_environment(monkeypatch):
    monkeypatch.setenv("VQTOUCH_PLUGINS", "vqtouch.plugins.evaluation.metrics")
    host = load_plugins(autoload=False, block=["metrics"])
    assert {"psnr", "ssim"} <= set(host.registry("metric").names())
    assert host.registry("metric").get("psnr").source.plugin == "vqtouch.plugins.evaluation.metrics"


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

    with pytest.raises(PluginError, match=r"plugin 'broken'.*vqtouch_register_metrics.*boom.*VQTOUCH_BLOCK_PLUGINS=broken"):
        load_plugins(autoload=False, extra=[make_plugin("broken", vqtouch_register_metrics)])


def test_duplicate_registration_across_plugins_names_both(make_plugin):
    @hookimpl
    def vqtouch_register_conditioners(register):
        class LabelConfig(PluginConfig):
            name: Literal["label"] = "label"
        register("label", lambda c, x: None, LabelConfig)

    with pytest.raises(PluginError, match=r"duplicate conditioner name 'label'.*plugin 'label' \(vqtouch .*\).*plugin 'dup'"):
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


class _Encoder(Encoder):
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
    pass


class _Discriminator(Discriminator):
    def forward(self, images_BCHW):
        return images_BCHW.mean(dim=(1, 2, 3))


# One minimal implementation per registration hook, registered through that hook by name.
MINIMAL = {
    "vqtouch_register_encoders": ("encoder", _Encoder),
    "vqtouch_register_quantizers": ("quantizer", _Quantizer),
    "vqtouch_register_clusterers": ("clusterer", _Clusterer),
    "vqtouch_register_datasets": ("dataset", _Dataset),
    "vqtouch_register_sensor_families": ("sensor_family", _Sensor),
    "vqtouch_register_generators": ("generator", _Generator),
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
        register("my-scene", {"stages": ["evaluate"], "metrics": [{"name": "psnr"}]}, description="mine")

    host = load_plugins(autoload=False, extra=[make_plugin("scenes_extra", vqtouch_register_scenes)])
    assert host.scene("my-scene").description == "mine"

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
    assert {row["kind"] for row in rows} >= {"conditioner", "metric", "scene"}
    assert all(row["version"] for row in rows if row["package"] == "vqtouch")

import json
import struct

import pytest
import torch
from torch import nn

from vqtouch.core import BuildContext, CheckpointError, hookimpl, load, load_plugins, read_metadata, save
from vqtouch.core.checkpoint import FORMAT_VERSION, atomic_write

CONTEXT = BuildContext(image_size=32, num_classes=5, cond_dim=16, latent_dim=8)


def _nn_components(host):
    """(kind, name) of every registered component that is a module and builds offline."""
    pairs = []
    for kind in ("conditioner", "encoder", "quantizer", "sensor_family", "generator", "clusterer"):
        for name in host.registry(kind).names():
            if (kind, name) != ("conditioner", "clip"):  # needs a weights file: tested in test_conditioners
                pairs.append((kind, name))
    return pairs


@pytest.mark.parametrize("kind, name", _nn_components(load_plugins(autoload=False)))
def test_every_module_component_round_trips(host, tmp_path, kind, name):
    component = host.build(kind, {"name": name}, CONTEXT)
    with torch.no_grad():
        for parameter in component.parameters():
            parameter.add_(torch.randn_like(parameter))  # make sure weights are not just the init
    path = save(component, tmp_path / f"{name}.safetensors", step=42, host=host)
    restored = load(path, host=host)
    assert type(restored) is type(component)
    assert restored.vqtouch_step == 42
    assert restored.vqtouch_spec.config == component.vqtouch_spec.config
    assert restored.vqtouch_spec.context == CONTEXT
    original, loaded = component.state_dict(), restored.state_dict()
    assert original.keys() == loaded.keys()
    for key in original:
        assert torch.equal(original[key], loaded[key]), key


def test_header_carries_everything_needed(host, tmp_path):
    component = host.build("conditioner", {"name": "label", "num_tokens": 2}, CONTEXT)
    metadata = read_metadata(save(component, tmp_path / "label.safetensors", step=7, host=host))
    assert metadata["format"] == "pt"
    assert metadata["vqtouch.format_version"] == FORMAT_VERSION
    assert metadata["vqtouch.component"] == "conditioner"
    assert metadata["vqtouch.plugin"] == "label"
    assert json.loads(metadata["vqtouch.config"]) == {"name": "label", "num_classes": 0, "num_tokens": 2}
    assert json.loads(metadata["vqtouch.context"])["num_classes"] == 5
    assert json.loads(metadata["vqtouch.plugin_source"])["distribution"] == "vqtouch"
    assert metadata["vqtouch.step"] == "7"


def test_plugin_metadata_hook_adds_namespaced_keys(tmp_path, make_plugin):
    @hookimpl
    def vqtouch_checkpoint_metadata(kind, name, config):
        return {"calib.sensor_serial": "A17"} if name == "label" else None

    host = load_plugins(autoload=False, extra=[make_plugin("calib", vqtouch_checkpoint_metadata)])
    component = host.build("conditioner", "label", CONTEXT)
    metadata = read_metadata(save(component, tmp_path / "x.safetensors", host=host))
    assert metadata["calib.sensor_serial"] == "A17"

    @hookimpl
    def vqtouch_checkpoint_metadata(kind, name, config):  # noqa: F811 - reserved key is refused
        return {"vqtouch.step": "999"}

    host = load_plugins(autoload=False, extra=[make_plugin("calib", vqtouch_checkpoint_metadata)])
    with pytest.raises(CheckpointError, match="not allowed"):
        save(host.build("conditioner", "label", CONTEXT), tmp_path / "y.safetensors", host=host)


def test_interrupted_save_keeps_previous_checkpoint(host, tmp_path):
    path = tmp_path / "ckpt.safetensors"
    component = host.build("conditioner", "label", CONTEXT)
    save(component, path, step=1, host=host)
    before = path.read_bytes()

    def crash(tmp):
        tmp.write_bytes(b"partial")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        atomic_write(path, crash)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["ckpt.safetensors"]  # no temporary left behind


def test_truncated_file_gives_one_line_error(host, tmp_path):
    path = save(host.build("conditioner", "label", CONTEXT), tmp_path / "c.safetensors", host=host)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError) as info:
        load(path, host=host)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize("content", [b"", b"not a checkpoint at all", struct.pack("<Q", 10**12) + b"{}",
                                     struct.pack("<Q", 2) + b"{]"])
def test_not_safetensors_gives_one_line_error(host, tmp_path, content):
    path = tmp_path / "bad.safetensors"
    path.write_bytes(content)
    with pytest.raises(CheckpointError) as info:
        load(path, host=host)
    message = str(info.value)
    assert message.startswith(str(path)) and "\n" not in message


def test_plain_safetensors_without_vqtouch_header(tmp_path, host):
    from safetensors.torch import save_file

    path = tmp_path / "plain.safetensors"
    save_file({"w": torch.zeros(2)}, str(path))
    with pytest.raises(CheckpointError, match="not a vqtouch checkpoint"):
        load(path, host=host)


def test_missing_file(host, tmp_path):
    with pytest.raises(CheckpointError, match="no such checkpoint file"):
        load(tmp_path / "nope.safetensors", host=host)


def test_missing_plugin_is_named(tmp_path):
    full = load_plugins(autoload=False)
    path = save(full.build("conditioner", "tactile", CONTEXT), tmp_path / "t.safetensors", host=full)
    without = load_plugins(autoload=False, block=["tactile"])
    with pytest.raises(CheckpointError, match=r"made by conditioner plugin 'tactile'.*not available here"):
        load(path, host=without)


def test_shape_mismatch_names_tensor(host, tmp_path):
    from safetensors.torch import save_model

    component = host.build("conditioner", "label", CONTEXT)
    metadata = read_metadata(save(component, tmp_path / "ok.safetensors", host=host))
    metadata["vqtouch.context"] = json.dumps({**json.loads(metadata["vqtouch.context"]), "num_classes": 6})
    save_model(component, str(tmp_path / "bad.safetensors"), metadata=metadata)
    with pytest.raises(CheckpointError, match=r"tensor 'embedding.weight' has shape \(5, 16\) in the file but "
                                              r"\(6, 16\) in the model"):
        load(tmp_path / "bad.safetensors", host=host)


def test_future_format_version_is_refused(host, tmp_path):
    from safetensors.torch import save_model

    component = host.build("conditioner", "label", CONTEXT)
    metadata = read_metadata(save(component, tmp_path / "ok.safetensors", host=host))
    save_model(component, str(tmp_path / "v9.safetensors"), metadata={**metadata, "vqtouch.format_version": "9"})
    with pytest.raises(CheckpointError, match="format version '9' is not supported"):
        load(tmp_path / "v9.safetensors", host=host)


def test_component_not_built_by_vqtouch_is_refused(tmp_path):
    with pytest.raises(CheckpointError, match="not built through vqtouch"):
        save(nn.Linear(2, 2), tmp_path / "x.safetensors")


def test_wrong_suffix_is_refused(host, tmp_path):
    with pytest.raises(CheckpointError, match="must end in .safetensors"):
        save(host.build("conditioner", "label", CONTEXT), tmp_path / "x.pt", host=host)


def test_no_pickle_anywhere_in_the_package(package_sources):
    for path in package_sources:
        text = path.read_text()
        assert "import pickle" not in text and "allow_pickle=True" not in text, path
        for line in text.splitlines():
            if "torch.load(" in line:
                assert "weights_only=True" in line, f"{path}: {line.strip()}"

import importlib.util
import json
import os
import struct
import sys
from pathlib import Path

import pytest
import torch
from torch import nn

import vqtouch.core.checkpoint as checkpoint_module
from vqtouch.core import BuildContext, CheckpointError, hookimpl, load, load_plugins, read_metadata, save
from vqtouch.core.checkpoint import FORMAT_VERSION, atomic_write
from vqtouch.core.plugin_manager import REGISTRY_KINDS
from vqtouch.plugins.testing import build_for_check, check_round_trip

CONTEXT = BuildContext(image_size=32, num_classes=5, cond_dim=16, latent_dim=8, codebook_size=16, code_grid=4)


def _load_contract_cases():
    # The built-ins' tiny options live with their contract tests; test modules cannot import each
    # other under --import-mode=importlib, so load that module by path.
    path = Path(__file__).with_name("test_plugin_contracts.py")
    spec = importlib.util.spec_from_file_location("plugin_contract_cases", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # pydantic resolves the module's annotations through sys.modules
    spec.loader.exec_module(module)
    return module


CASES = _load_contract_cases()
MODULE_KINDS = [kind.name for kind in REGISTRY_KINDS if issubclass(kind.base_type, nn.Module)]
MODULE_ENTRIES = [(kind, name) for kind in MODULE_KINDS for name in load_plugins(autoload=False).registry(kind).names()]


def test_every_module_kind_is_round_tripped():
    assert set(MODULE_KINDS) == {
        "autoencoder",
        "quantizer",
        "discriminator",
        "conditioner",
        "sensor_family",
        "generator",
        "clusterer",
    }
    assert {kind for kind, _ in MODULE_ENTRIES} >= {
        "autoencoder",
        "quantizer",
        "discriminator",
        "conditioner",
        "sensor_family",
    }


@pytest.mark.parametrize("kind, name", MODULE_ENTRIES)
def test_every_module_component_round_trips(host, tmp_path, tmp_path_factory, kind, name):
    """Built with tiny options, its weights moved off their initial values, saved and loaded: the reloaded
    component has the same state and computes the same outputs (vqtouch.plugins.testing.check_round_trip)."""
    case = CASES.builtin_case(kind, name, tmp_path_factory)
    component = build_for_check(host, kind, name, case["options"], CONTEXT, inputs=case.get("inputs"))
    restored = check_round_trip(host, component, tmp_path, step=42)
    assert restored.vqtouch_step == 42 and restored.vqtouch_spec.context == CONTEXT


# A checker that cannot fail proves nothing: break the round trip and watch it fail.
STATEFUL = [("autoencoder", "vqgan"), ("quantizer", "ema_vq"), ("discriminator", "patchgan"), ("conditioner", "label")]


@pytest.mark.parametrize("kind, name", STATEFUL)
def test_round_trip_check_fails_when_load_skips_the_weights(host, tmp_path, tmp_path_factory, monkeypatch, kind, name):
    monkeypatch.setattr(checkpoint_module, "load_state_strict", lambda module, tensors, path: None)
    component = build_for_check(host, kind, name, CASES.builtin_case(kind, name, tmp_path_factory)["options"], CONTEXT)
    with pytest.raises(AssertionError, match=f"{kind} '{name}': tensor .* changed in the checkpoint round trip"):
        check_round_trip(host, component, tmp_path)


@pytest.mark.parametrize("kind, name", STATEFUL)
def test_round_trip_check_fails_when_save_drops_a_tensor(host, tmp_path, tmp_path_factory, monkeypatch, kind, name):
    from safetensors.torch import save_file

    def save_all_but_one(model, filename, metadata=None):
        tensors = {key: value.contiguous() for key, value in model.state_dict().items()}
        tensors.pop(sorted(tensors)[-1])
        save_file(tensors, filename, metadata=metadata)

    monkeypatch.setattr(checkpoint_module, "save_model", save_all_but_one)
    component = build_for_check(host, kind, name, CASES.builtin_case(kind, name, tmp_path_factory)["options"], CONTEXT)
    with pytest.raises(AssertionError, match=r"round trip failed: CheckpointError: .*missing 1 tensor"):
        check_round_trip(host, component, tmp_path)


def test_round_trip_check_fails_when_the_header_loses_an_option(host, tmp_path, monkeypatch):
    """A sensor has no tensors: what it is lives in its options, so losing one must show."""
    original = checkpoint_module.checkpoint_metadata

    def forgetful(component, step, host=None, extra=None):
        metadata = original(component, step, host, extra)
        config = json.loads(metadata["vqtouch.config"])
        config.pop("variant", None)
        return {**metadata, "vqtouch.config": json.dumps(config)}

    monkeypatch.setattr(checkpoint_module, "checkpoint_metadata", forgetful)
    variant = {"response_scale": 0.5, "noise_std": 0.05}
    component = build_for_check(host, "sensor_family", "gelsight", {"variant": variant}, CONTEXT)
    with pytest.raises(AssertionError, match="reloaded config .* differs"):
        check_round_trip(host, component, tmp_path)


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


def test_disk_full_gives_one_line_error_and_keeps_the_previous_file(host, tmp_path, monkeypatch):
    import errno

    path = tmp_path / "ckpt.safetensors"
    component = host.build("conditioner", "label", CONTEXT)
    save(component, path, step=1, host=host)
    before = path.read_bytes()

    def no_space(module, filename, metadata=None):
        with open(filename, "wb") as handle:
            handle.write(b"half")  # part of the file made it to disk
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(checkpoint_module, "save_model", no_space)
    with pytest.raises(CheckpointError) as info:
        save(component, path, step=2, host=host)
    assert str(info.value) == (
        f"{path}: could not write the checkpoint file: No space left on device; free disk "
        "space and run again (nothing was replaced)"
    )
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["ckpt.safetensors"]


def test_a_safetensors_write_error_is_one_line_too(host, tmp_path, monkeypatch):
    from safetensors import SafetensorError

    def read_only(module, filename, metadata=None):
        raise SafetensorError(
            f'Error while serializing: I/O error: Read-only file system (os error 30) at path "{tmp_path}/.tmpAbCdEf"'
        )

    monkeypatch.setattr(checkpoint_module, "save_model", read_only)
    with pytest.raises(CheckpointError) as info:
        save(host.build("conditioner", "label", CONTEXT), tmp_path / "c.safetensors", host=host)
    assert str(info.value) == (
        f"{tmp_path / 'c.safetensors'}: could not write the checkpoint file: Read-only file "
        f"system; make {tmp_path} writable or write elsewhere (nothing was replaced)"
    )


def test_written_files_follow_the_umask(host, tmp_path):
    previous = os.umask(0o027)
    try:
        text = atomic_write(tmp_path / "notes.json", lambda tmp: tmp.write_text("{}"))
        # safetensors writes its own temporary (mode 0600) and renames it onto atomic_write's.
        weights = save(host.build("conditioner", "label", CONTEXT), tmp_path / "c.safetensors", host=host)
    finally:
        os.umask(previous)
    assert [oct(path.stat().st_mode & 0o777) for path in (text, weights)] == [oct(0o640)] * 2


def test_truncated_file_gives_one_line_error(host, tmp_path):
    path = save(host.build("conditioner", "label", CONTEXT), tmp_path / "c.safetensors", host=host)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError) as info:
        load(path, host=host)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize(
    "content", [b"", b"not a checkpoint at all", struct.pack("<Q", 10**12) + b"{}", struct.pack("<Q", 2) + b"{]"]
)
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


def test_missing_plugin_is_named_with_its_distribution(tmp_path):
    from vqtouch.core import __version__

    full = load_plugins(autoload=False)
    path = save(full.build("conditioner", "tactile", CONTEXT), tmp_path / "t.safetensors", host=full)
    without = load_plugins(autoload=False, block=["tactile"])
    with pytest.raises(CheckpointError) as info:
        load(path, host=without)
    assert str(info.value) == (
        f"{path}: made by conditioner 'tactile' from vqtouch {__version__}, which is not "
        "installed here; pip install vqtouch"
    )


def test_missing_third_party_plugin_names_the_distribution_from_the_header(tmp_path, third_party_conditioner):
    from safetensors.torch import save_model

    with_plugin = load_plugins(autoload=False, extra=[third_party_conditioner])
    component = with_plugin.build("conditioner", "x", CONTEXT)
    metadata = read_metadata(save(component, tmp_path / "ok.safetensors", host=with_plugin))
    # What an installed distribution records (an in-memory module has none).
    metadata["vqtouch.plugin_source"] = json.dumps({"plugin": "pkg_plugin", "distribution": "pkg", "version": "1.0"})
    save_model(component, str(tmp_path / "x.safetensors"), metadata=metadata)
    with pytest.raises(CheckpointError) as info:
        load(tmp_path / "x.safetensors", host=load_plugins(autoload=False))
    assert str(info.value).endswith(
        "made by conditioner 'x' from pkg 1.0, which is not installed here; pip install pkg"
    )
    assert isinstance(load(tmp_path / "x.safetensors", host=with_plugin), third_party_conditioner.Extra)


def test_shape_mismatch_names_tensor(host, tmp_path):
    from safetensors.torch import save_model

    component = host.build("conditioner", "label", CONTEXT)
    metadata = read_metadata(save(component, tmp_path / "ok.safetensors", host=host))
    metadata["vqtouch.context"] = json.dumps({**json.loads(metadata["vqtouch.context"]), "num_classes": 6})
    save_model(component, str(tmp_path / "bad.safetensors"), metadata=metadata)
    with pytest.raises(
        CheckpointError,
        match=r"tensor 'embedding.weight' has shape \(5, 16\) in the file but "
        r"\(6, 16\) in the model",
    ):
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


def test_a_callers_header_entries_are_saved_and_must_be_namespaced(host, tmp_path):
    from vqtouch.core import read_metadata

    sensor = host.build("sensor_family", "gelsight")
    path = save(sensor, tmp_path / "s.safetensors", host=host, metadata={"adaptation.shots": "50"})
    assert read_metadata(path)["adaptation.shots"] == "50"
    for bad in ({"vqtouch.step": "3"}, {"adaptation.shots": 50}):
        with pytest.raises(CheckpointError, match="from the caller is not allowed: keys must be namespaced"):
            save(sensor, tmp_path / "t.safetensors", host=host, metadata=bad)

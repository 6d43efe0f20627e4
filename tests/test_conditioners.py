"""Contract tests over every registered conditioner, plus each built-in's own properties."""

import sys

import pytest
import torch

from vqtouch.core import BuildContext, ConfigError, MissingWeightsError, PluginError, load, load_plugins, save

CONTEXT = BuildContext(image_size=32, num_classes=4, cond_dim=16)


@pytest.fixture(scope="module")
def build(host, tmp_path_factory):
    """``build(name, context)``: the conditioner with its default options, plus the local files it
    needs (tactile_codes: a tiny source tokenizer)."""
    import generator_runs

    def build_conditioner(name, context=CONTEXT):
        config = {"name": name}
        if name == "tactile_codes":
            config["tokenizer"] = str(generator_runs.tiny_tokenizer_folder(tmp_path_factory.getbasetemp()))
        return host.build("conditioner", config, context)

    return build_conditioner


def example_condition(conditioner, batch):
    """The contract checks' example batch for the conditioner's sample key (labels, images or texts)."""
    from vqtouch.plugins.testing import example_condition as contract_example

    if conditioner.sample_key == "label":
        return torch.arange(batch) % conditioner.num_classes
    return contract_example(conditioner, batch, BuildContext(image_size=32))


OFFLINE_CONDITIONERS = [
    name for name in load_plugins(autoload=False).registry("conditioner").names() if name not in ("clip", "text")
]  # these two need a local open_clip weights file


# The shape / null-token / drop-mask contract of every conditioner is checked by
# vqtouch.plugins.testing.check_plugin in test_plugin_contracts.py.


@pytest.mark.parametrize("name", OFFLINE_CONDITIONERS)
def test_conditioner_gradients_reach_parameters(build, name):
    conditioner = build(name)
    condition = conditioner(example_condition(conditioner, 2))
    loss = condition.tokens_BND.square().sum()
    if condition.grid_BDhw is not None:  # the aligned grid is an output too (image conditioners)
        loss = loss + condition.grid_BDhw.square().sum()
    loss.backward()
    trainable = [p for n, p in conditioner.named_parameters() if n != "null_tokens_ND"]
    assert trainable and all(p.grad is not None and torch.isfinite(p.grad).all() for p in trainable)


@pytest.mark.parametrize("name", OFFLINE_CONDITIONERS)
def test_conditioner_under_bf16_autocast_is_finite(build, name):
    conditioner = build(name)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = conditioner(example_condition(conditioner, 2))
    assert torch.isfinite(out.tokens_BND.float()).all()


@pytest.mark.parametrize("value", [0.0, 1.0])
def test_tactile_conditioner_on_constant_saturated_images(host, value):
    conditioner = host.build("conditioner", "tactile", CONTEXT)
    out = conditioner(torch.full((1, 3, 32, 32), value))
    assert torch.isfinite(out.tokens_BND).all()


def test_label_out_of_range_is_a_clear_error(host):
    conditioner = host.build("conditioner", "label", CONTEXT)
    with pytest.raises(ValueError, match=r"labels must be in \[0, 4\); got min 0, max 4"):
        conditioner(torch.tensor([0, 4]))
    with pytest.raises(ValueError, match="1-D integer tensor"):
        conditioner(torch.tensor([0.5]))


def test_label_needs_class_count(host):
    with pytest.raises(ConfigError, match="set conditioner.num_classes=N"):
        host.build("conditioner", "label", BuildContext(num_classes=0))
    assert host.build("conditioner", {"name": "label", "num_classes": 9}, BuildContext()).num_classes == 9


def test_tactile_rejects_wrong_shape(host):
    conditioner = host.build("conditioner", "tactile", CONTEXT)
    with pytest.raises(ValueError, match=r"expects images \(B, 3, H, W\)"):
        conditioner(torch.rand(2, 32, 32))


# -- clip: needs a local weights file; tests save a tiny open_clip model and load it back --------

TINY_CLIP = {
    "embed_dim": 32,
    "vision_cfg": {"image_size": 64, "layers": 2, "width": 64, "patch_size": 16, "head_width": 32},
    "text_cfg": {"context_length": 77, "vocab_size": 49408, "width": 64, "heads": 2, "layers": 2},
}


@pytest.fixture(scope="module")
def tiny_clip_file(tmp_path_factory):
    open_clip = pytest.importorskip("open_clip")
    from safetensors.torch import save_file

    torch.manual_seed(1)
    model = open_clip.create_model("ViT-S-32", pretrained=None, **TINY_CLIP)
    path = tmp_path_factory.mktemp("clip") / "tiny_clip.safetensors"
    save_file({k: v.contiguous() for k, v in model.state_dict().items()}, str(path))
    return path, model


def test_clip_without_weights_names_file_and_ways_to_provide(host, monkeypatch):
    monkeypatch.delenv("VQTOUCH_CLIP_CKPT", raising=False)
    monkeypatch.delenv("VQTOUCH_WEIGHTS_DIR", raising=False)
    with pytest.raises(MissingWeightsError) as info:
        host.build("conditioner", "clip", CONTEXT)
    message = str(info.value)
    for needle in (
        "open_clip_model.safetensors",
        "checkpoint option",
        "VQTOUCH_CLIP_CKPT",
        "VQTOUCH_WEIGHTS_DIR",
        "never downloads",
    ):
        assert needle in message


def test_clip_loads_local_weights_and_stays_frozen(host, tiny_clip_file, tmp_path):
    path, reference = tiny_clip_file
    config = {
        "name": "clip",
        "architecture": "ViT-S-32",
        "checkpoint": str(path),
        "model_overrides": TINY_CLIP,
        "num_tokens": 2,
    }
    conditioner = host.build("conditioner", config, CONTEXT)
    images = torch.rand(2, 3, 40, 40)
    out = conditioner(images)
    assert out.tokens_BND.shape == (2, 2, 16)
    # The frozen encoder really holds the file's weights: embeddings match the reference model.
    resized = torch.nn.functional.interpolate(images, size=(64, 64), mode="bicubic", antialias=True).clamp(0, 1)
    normalised = (resized - conditioner.mean_C[:, None, None]) / conditioner.std_C[:, None, None]
    expected = torch.nn.functional.normalize(reference.eval().encode_image(normalised), dim=-1)
    got = conditioner.project(expected).view(2, 2, 16)
    torch.testing.assert_close(out.tokens_BND, got, atol=1e-5, rtol=1e-5)
    # Only the projection and null tokens are trainable / saved; CLIP stays out of the checkpoint.
    assert set(conditioner.state_dict()) == {"null_tokens_ND", "project.weight", "project.bias"}
    out.tokens_BND.sum().backward()
    assert all(p.grad is None for p in conditioner.encoder.network.parameters())
    # The encoder is held by vqtouch.plugins.utils.frozen.FrozenModule: training the conditioner
    # leaves it frozen, in eval.
    conditioner.train().requires_grad_(True)
    assert not conditioner.encoder.network.training
    assert not any(p.requires_grad for p in conditioner.encoder.network.parameters())
    restored = load(save(conditioner, tmp_path / "clip.safetensors", host=host), host=host)
    torch.testing.assert_close(restored(images).tokens_BND, out.tokens_BND)


def test_clip_without_open_clip_names_the_extra(host, monkeypatch, tmp_path):
    weights = tmp_path / "open_clip_model.safetensors"
    weights.write_bytes(b"unused")  # the weights are found; only the package is missing
    monkeypatch.setitem(sys.modules, "open_clip", None)  # makes `import open_clip` raise ModuleNotFoundError
    with pytest.raises(PluginError) as info:
        host.build("conditioner", {"name": "clip", "checkpoint": str(weights)}, CONTEXT)
    assert str(info.value) == "conditioner 'clip' needs open_clip_torch: pip install 'vqtouch[clip]'"


def test_clip_with_a_broken_open_clip_says_it_is_installed(host, monkeypatch, tmp_path):
    import builtins

    weights = tmp_path / "open_clip_model.safetensors"
    weights.write_bytes(b"unused")
    real_import = builtins.__import__

    def failing_import(name, *args, **kwargs):
        if name == "open_clip":  # what a torchvision built for another torch does to open_clip
            raise ImportError("operator torchvision::nms does not exist")
        return real_import(name, *args, **kwargs)

    monkeypatch.delitem(sys.modules, "open_clip", raising=False)
    monkeypatch.setattr(builtins, "__import__", failing_import)
    with pytest.raises(
        PluginError,
        match=r"installed but does not import \(operator torchvision::nms does not "
        r"exist\).*pip install 'vqtouch\[clip\]'",
    ) as info:
        host.build("conditioner", {"name": "clip", "checkpoint": str(weights)}, CONTEXT)
    assert "\n" not in str(info.value)


def test_clip_with_wrong_weights_file_is_a_clear_error(host, tmp_path):
    from safetensors.torch import save_file

    path = tmp_path / "wrong.safetensors"
    save_file({"not_clip": torch.zeros(1)}, str(path))
    with pytest.raises(MissingWeightsError, match="does not hold ViT-S-32 weights"):
        host.build(
            "conditioner",
            {"name": "clip", "architecture": "ViT-S-32", "checkpoint": str(path), "model_overrides": TINY_CLIP},
            CONTEXT,
        )


def test_clip_unknown_architecture(host, tiny_clip_file):
    path, _ = tiny_clip_file
    with pytest.raises(ConfigError, match="unknown open_clip architecture 'ViT-B-33'.*did you mean"):
        host.build("conditioner", {"name": "clip", "architecture": "ViT-B-33", "checkpoint": str(path)}, CONTEXT)


#: The sensor tag reads the sensor index that few-shot fine-tuning gives its mixed rows, not a dataset's entry.
DATASET_CONDITIONERS = [name for name in OFFLINE_CONDITIONERS if name != "sensor"]


@pytest.mark.parametrize("name", DATASET_CONDITIONERS)
def test_each_conditioner_reads_its_own_entry_of_a_dataset_batch(host, build, name):
    """`sample_key` routes a collated batch of procedural samples (paired: a DIGIT image per GelSight
    one) to the right conditioner input."""
    from vqtouch.plugins.training.batches import collate_samples

    dataset = host.build(
        "dataset",
        {"name": "procedural", "num_samples": 3, "image_size": 32},
        BuildContext(image_size=32),
        sensor=host.build("sensor_family", "gelsight"),
        paired_sensor=host.build("sensor_family", "digit"),
    )
    batch = collate_samples([dataset[i] for i in range(3)])
    conditioner = build(name, BuildContext(image_size=32, num_classes=dataset.num_classes, cond_dim=16))
    condition = conditioner.condition_of(batch)
    assert condition is batch[conditioner.sample_key]
    assert conditioner(condition).tokens_BND.shape == (3, conditioner.num_tokens, 16)
    with pytest.raises(KeyError, match=rf"reads samples' '{conditioner.sample_key}', which this batch lacks"):
        conditioner.condition_of({key: value for key, value in batch.items() if key != conditioner.sample_key})

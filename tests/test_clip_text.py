"""Properties of the ``text`` conditioner: open_clip's frozen text tower from a local weights file.

Every test here uses a TINY, RANDOMLY INITIALISED open_clip model (``ViT-S-32`` shrunk with
``model_overrides``: a 2-layer, 64-wide text transformer), saved to a temporary safetensors file
and loaded back through the conditioner.  It is not CLIP and nothing here is pretrained: these
tests check the plumbing (which states are read, what is frozen, what is saved, what fails how),
never the quality of a text embedding.  They are skipped when open_clip (the ``clip`` extra) is
not installed.  The shape / null-token / checkpoint contracts are also checked with every other
plugin in test_plugin_contracts.py and test_checkpoint.py.
"""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch

from vqtouch.core import BuildContext, ConfigError, MissingWeightsError, PluginError, load, load_plugins, save
from vqtouch.plugins.training.batches import collate_samples

CONTEXT = BuildContext(image_size=32, cond_dim=16)
from metric_weights import TINY_RANDOM_CLIP  # noqa: E402  (registered by conftest)

TEXTS = ["a smooth sphere pressed into the gel", "a coarse woven fabric", "a sharp metal edge"]


@pytest.fixture(scope="module")
def host():
    """Built-in plugins with this conditioner's module also loaded explicitly: a no-op once the installed
    metadata lists its entry point, so these tests do not depend on a reinstall (test_plugin_contracts.py
    checks the registration itself)."""
    return load_plugins(autoload=False, extra=["vqtouch.conditioners.clip_text_plugin"])


def _save_tiny_random_model(open_clip, path, **overrides):
    from safetensors.torch import save_file

    torch.manual_seed(3)
    model = open_clip.create_model("ViT-S-32", pretrained=None, **{**TINY_RANDOM_CLIP, **overrides})
    save_file({k: v.contiguous() for k, v in model.state_dict().items()}, str(path))
    return model.eval()


@pytest.fixture(scope="module")
def tiny_random_clip(tmp_path_factory):
    """(path, reference model): a tiny randomly initialised open_clip model written to a safetensors file."""
    open_clip = pytest.importorskip("open_clip")
    path = tmp_path_factory.mktemp("text") / "tiny_random_clip.safetensors"
    return path, _save_tiny_random_model(open_clip, path)


def _options(path, **more):
    return {
        "name": "text",
        "architecture": "ViT-S-32",
        "checkpoint": str(path),
        "model_overrides": TINY_RANDOM_CLIP,
        "context_length": 8,
        **more,
    }


@pytest.fixture(scope="module")
def conditioner(host, tiny_random_clip):
    return host.build("conditioner", _options(tiny_random_clip[0]), CONTEXT)


def test_tokens_have_the_documented_shape_dtype_and_are_finite(conditioner):
    assert conditioner.sample_key == "text" and conditioner.num_tokens == 8 and conditioner.cond_dim == 16
    texts = [*TEXTS, "", "gel " * 500, "Ünïcödé wörds 触觉 センサー"]
    tokens = conditioner(texts).tokens_BND
    assert tokens.shape == (6, 8, 16) and tokens.dtype == torch.float32
    assert torch.isfinite(tokens).all()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert torch.isfinite(conditioner(texts).tokens_BND.float()).all()


def test_tokens_are_the_loaded_towers_final_hidden_states_projected(conditioner, tiny_random_clip):
    """Read independently of open_clip's forward_intermediates: embeddings + position embeddings, the
    transformer with its causal mask, the final LayerNorm; and CLIP's own pooled text embedding is the
    end-of-text state times the text projection, so these are the states encode_text pools from."""
    _, reference = tiny_random_clip
    ids = conditioner.token_ids(TEXTS[:2])
    full = torch.nn.functional.pad(ids, (0, 77 - 8))
    with torch.no_grad():
        x = reference.token_embedding(full) + reference.positional_embedding
        expected = reference.ln_final(reference.transformer(x, attn_mask=reference.attn_mask))[:, :8]
        pooled = expected[torch.arange(2), ids.argmax(-1)] @ reference.text_projection
        torch.testing.assert_close(pooled, reference.encode_text(full), atol=1e-5, rtol=1e-5)
        hidden = conditioner.hidden_states(TEXTS[:2])
        torch.testing.assert_close(hidden, expected, atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(conditioner.encode(TEXTS[:2]), conditioner.project(expected), atol=1e-5, rtol=1e-5)


def test_frozen_tower_gets_no_gradient_while_the_projection_does(host, tiny_random_clip):
    built = host.build("conditioner", _options(tiny_random_clip[0]), CONTEXT)
    network = built.encoder.network
    # Training the conditioner (train mode, everything trainable) leaves the tower frozen and in eval mode.
    built.train().requires_grad_(True)
    assert not network.training and not any(p.requires_grad for p in network.parameters())
    built(TEXTS).tokens_BND.square().sum().backward()
    assert all(p.grad is None for p in network.parameters())
    for parameter in (built.project.weight, built.project.bias):
        assert parameter.grad is not None and torch.isfinite(parameter.grad).all() and parameter.grad.abs().sum() > 0
    # Only the projection and the null tokens are trainable and saved; the tower (image tower dropped) is not.
    assert {name for name, p in built.named_parameters() if p.requires_grad} == {
        "null_tokens_ND",
        "project.weight",
        "project.bias",
    }
    assert set(built.state_dict()) == {"null_tokens_ND", "project.weight", "project.bias"}
    assert not any(name.startswith("visual.") for name, _ in network.named_parameters())


def test_tokens_are_deterministic_and_tell_texts_apart(host, conditioner, tiny_random_clip):
    with torch.no_grad():
        first = conditioner.encode(TEXTS)
        second = conditioner.encode(list(TEXTS))
        # A text's tokens do not depend on the other texts of its batch (every text is padded to the same length).
        alone = conditioner.encode([TEXTS[1]])
        # Another build from the same file gives the same frozen states.
        again = host.build("conditioner", _options(tiny_random_clip[0]), CONTEXT)
        hidden, hidden_again = conditioner.hidden_states(TEXTS), again.hidden_states(TEXTS)
    torch.testing.assert_close(first, second, atol=0, rtol=0)
    torch.testing.assert_close(alone[0], first[1], atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(hidden, hidden_again, atol=0, rtol=0)
    for i, j in [(0, 1), (0, 2), (1, 2)]:
        assert (first[i] - first[j]).abs().max() > 1e-3, (TEXTS[i], TEXTS[j])


def test_token_ids_are_open_clips_bpe_truncated_with_end_of_text(conditioner):
    sot, eot = 49406, 49407
    ids = conditioner.token_ids(["a smooth sphere", "one two three four five six seven eight nine ten"])
    assert ids.shape == (2, 8) and ids.dtype == torch.long
    assert ids[0].tolist()[:2] == [sot, 320] and ids[0, 4] == eot and ids[0, 5:].eq(0).all()  # 320: BPE "a</w>"
    assert ids[1, 0] == sot and ids[1, -1] == eot and ids[1, 1:-1].ne(0).all()  # truncated: end-of-text kept last
    with torch.no_grad():
        short, longer = (
            conditioner.encode(["one two three four five six"]),
            conditioner.encode(["one two three four five six seven"]),
        )
    # Same first 7 ids (causal tower): same first 7 tokens; the last differs (a word vs end-of-text there).
    torch.testing.assert_close(longer[:, :7], short[:, :7], atol=1e-6, rtol=1e-5)


def test_missing_weights_file_is_a_one_line_error_naming_the_file_and_how_to_give_it(host, monkeypatch, tmp_path):
    pytest.importorskip("open_clip")
    monkeypatch.delenv("VQTOUCH_CLIP_CKPT", raising=False)
    monkeypatch.delenv("VQTOUCH_WEIGHTS_DIR", raising=False)
    with pytest.raises(MissingWeightsError) as info:
        host.build("conditioner", "text", CONTEXT)
    message = str(info.value)
    assert "\n" not in message
    for needle in (
        "conditioner 'text'",
        "open_clip_model.safetensors",
        "checkpoint option",
        "generator.conditioners.0.checkpoint",
        "VQTOUCH_CLIP_CKPT",
        "VQTOUCH_WEIGHTS_DIR",
        "never downloads",
    ):
        assert needle in message, needle
    missing = tmp_path / "nowhere.safetensors"
    with pytest.raises(MissingWeightsError) as info:
        host.build("conditioner", {"name": "text", "checkpoint": str(missing)}, CONTEXT)
    assert "\n" not in str(info.value) and str(missing) in str(info.value) and "checkpoint" in str(info.value)


def test_null_condition_is_learned_and_replaces_dropped_rows(conditioner):
    null = conditioner.null(3)
    assert null.tokens_BND.shape == (3, 8, 16) and null.is_null_B.all()
    torch.testing.assert_close(null.tokens_BND, conditioner.null_tokens_ND.expand(3, -1, -1))
    drop = torch.tensor([True, False, True])
    out = conditioner(TEXTS, drop)
    assert out.is_null_B.tolist() == drop.tolist()
    torch.testing.assert_close(out.tokens_BND[drop], conditioner.null_tokens_ND.expand(2, -1, -1))
    torch.testing.assert_close(out.tokens_BND[1], conditioner.encode(TEXTS)[1])
    assert (out.tokens_BND[0] - conditioner.encode(TEXTS)[0]).abs().max() > 1e-3  # the null is not the text
    assert conditioner.null_tokens_ND.requires_grad and "null_tokens_ND" in conditioner.state_dict()


def test_checkpoint_round_trip_rebuilds_the_tower_from_the_file(host, tiny_random_clip, tmp_path):
    built = host.build("conditioner", _options(tiny_random_clip[0]), CONTEXT)
    with torch.no_grad():  # move the trainable weights off their initial values
        for parameter in built.parameters():
            parameter.add_(torch.randn_like(parameter))
    path = save(built, tmp_path / "text.safetensors", host=host)
    restored = load(path, host=host)
    assert type(restored).__name__ == "TextConditioner" and restored.num_tokens == 8
    with torch.no_grad():
        torch.testing.assert_close(restored(TEXTS).tokens_BND, built(TEXTS).tokens_BND, atol=0, rtol=0)
    # The checkpoint is the projection and the null tokens only: far smaller than the tower it does not copy.
    assert path.stat().st_size < tiny_random_clip[0].stat().st_size / 20


def test_parses_a_users_string_and_reads_a_batchs_texts(conditioner):
    text = conditioner.parse_condition("a rough stone", image_size=32)
    assert text == "a rough stone"
    batch = collate_samples([{"text": text}, {"text": "a smooth sphere"}])
    assert conditioner.condition_of(batch) == ["a rough stone", "a smooth sphere"]
    assert conditioner(conditioner.condition_of(batch)).tokens_BND.shape == (2, 8, 16)
    with pytest.raises(ValueError, match="expects a list of B strings, got str"):
        conditioner.encode("a single string")
    with pytest.raises(ValueError, match="got a list with non-strings"):
        conditioner.encode(["a", 3])


@pytest.mark.parametrize(
    "architecture, needle", [("ViT-B-16-SigLIP", "SigLIP"), ("xlm-roberta-base-ViT-B-32", "xlm-roberta-base")]
)
def test_tokenizers_that_would_be_downloaded_are_refused(host, tiny_random_clip, architecture, needle):
    with pytest.raises(ConfigError, match=f"{needle}.*never downloads") as info:
        host.build(
            "conditioner",
            {"name": "text", "architecture": architecture, "checkpoint": str(tiny_random_clip[0])},
            CONTEXT,
        )
    assert "\n" not in str(info.value)


def test_context_length_beyond_the_models_is_refused(host, tmp_path):
    open_clip = pytest.importorskip("open_clip")
    short = {**TINY_RANDOM_CLIP, "text_cfg": {**TINY_RANDOM_CLIP["text_cfg"], "context_length": 6}}
    path = tmp_path / "tiny_random_short_context.safetensors"
    _save_tiny_random_model(open_clip, path, text_cfg=short["text_cfg"])
    with pytest.raises(ConfigError, match="context_length=8 exceeds ViT-S-32's context length 6"):
        host.build("conditioner", _options(path, model_overrides=short), CONTEXT)
    assert host.build("conditioner", _options(path, model_overrides=short, context_length=6), CONTEXT)(
        TEXTS
    ).tokens_BND.shape == (3, 6, 16)


def test_unknown_architecture_and_wrong_file_are_clear_errors(host, tiny_random_clip, tmp_path):
    from safetensors.torch import save_file

    with pytest.raises(
        ConfigError, match="conditioner 'text': unknown open_clip architecture 'ViT-S-33'.*did you mean"
    ):
        host.build("conditioner", _options(tiny_random_clip[0], architecture="ViT-S-33"), CONTEXT)
    wrong = tmp_path / "wrong.safetensors"
    save_file({"not_clip": torch.zeros(1)}, str(wrong))
    with pytest.raises(MissingWeightsError, match="conditioner 'text': .* does not hold ViT-S-32 weights"):
        host.build("conditioner", _options(wrong), CONTEXT)


def test_without_open_clip_names_the_extra(host, monkeypatch, tmp_path):
    weights = tmp_path / "open_clip_model.safetensors"
    weights.write_bytes(b"unused")  # the weights are found; only the package is missing
    monkeypatch.setitem(sys.modules, "open_clip", None)  # makes `import open_clip` raise ModuleNotFoundError
    with pytest.raises(PluginError) as info:
        host.build("conditioner", {"name": "text", "checkpoint": str(weights)}, CONTEXT)
    assert str(info.value) == "conditioner 'text' needs open_clip_torch: pip install 'vqtouch[clip]'"


PROBE = """
import sys
from vqtouch.core import BuildContext, load_plugins
host = load_plugins(extra=["vqtouch.conditioners.clip_text_plugin"])  # a no-op once the entry point is installed
host.build("conditioner", "label", BuildContext(num_classes=3, cond_dim=8))
host.build("conditioner", "text_scratch", BuildContext(cond_dim=8))
print("BEFORE:" + str("open_clip" in sys.modules))
try:
    host.build("conditioner", "text", BuildContext(cond_dim=8))
except Exception as exc:
    print("ERROR:" + type(exc).__name__)
print("AFTER:" + str("open_clip" in sys.modules))
"""


def test_open_clip_is_imported_only_when_the_text_conditioner_is_built():
    """In a fresh interpreter: loading plugins and building label/text_scratch never imports open_clip;
    building ``text`` does (and then stops at its missing weights file)."""
    pytest.importorskip("open_clip")
    result = subprocess.run(
        [sys.executable, "-c", PROBE],
        capture_output=True,
        text=True,
        timeout=300,
        env={"VQTOUCH_DISABLE_PLUGIN_AUTOLOAD": "1", "PATH": "/usr/bin:/bin"},
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.strip().splitlines()[-3:] == ["BEFORE:False", "ERROR:MissingWeightsError", "AFTER:True"]

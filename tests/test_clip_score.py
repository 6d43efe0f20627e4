"""The ``clip_score`` metric: CLIP-space consistency of generated tactile images with their conditions.

Every test here uses a TINY, RANDOMLY INITIALISED open_clip model (``ViT-S-32`` shrunk with
``model_overrides``), saved to a temporary safetensors file and loaded back through the metric.  It is
not CLIP and nothing here is pretrained: these tests check the plumbing (what is embedded how, what is
compared with what, what is reported and what is skipped why) against open_clip called directly, never
what a CLIP score of a tactile image is worth.  They are skipped when open_clip (the ``clip`` extra) is
not installed.  The metric contract (identical images score best, updates accumulate, reset forgets) is
checked with every other metric in test_plugin_contracts.py.
"""

from __future__ import annotations

import json
import sys

import pytest
import torch
import torch.nn.functional as F

from vqtouch.core import ConfigError, SkippedMetric, load_plugins
from vqtouch.plugins.evaluation.metric_set import MetricSet
from vqtouch.plugins.cli.app import main

from generator_runs import train_args  # noqa: E402  (registered by conftest)

HOST = load_plugins(autoload=False)
from metric_weights import TINY_RANDOM_CLIP  # noqa: E402  (registered by conftest)

CLASS_NAMES = ["sphere", "edge", "ridge"]


@pytest.fixture(scope="module")
def tiny_clip(tmp_path_factory):
    """(path, reference model): a tiny randomly initialised open_clip model written to a safetensors file."""
    open_clip = pytest.importorskip("open_clip")
    from safetensors.torch import save_file

    with torch.random.fork_rng():
        torch.manual_seed(5)
        model = open_clip.create_model("ViT-S-32", pretrained=None, **TINY_RANDOM_CLIP)
    path = tmp_path_factory.mktemp("clip") / "tiny_random_clip.safetensors"
    save_file({k: v.contiguous() for k, v in model.state_dict().items()}, str(path))
    return path, model.eval()


def options(path, **more):
    """The clip_score block for the tiny model in ``path``."""
    return {
        "name": "clip_score",
        "architecture": "ViT-S-32",
        "checkpoint": str(path),
        "model_overrides": TINY_RANDOM_CLIP,
        **more,
    }


@pytest.fixture(scope="module")
def metric(tiny_clip):
    return HOST.build("metric", options(tiny_clip[0]))


def smooth_images(count: int, seed: int, size: int = 32) -> torch.Tensor:
    """``count`` distinct smooth RGB images (random 4 x 4 colour fields, upsampled) in [0, 1]."""
    coarse = torch.rand(count, 3, 4, 4, generator=torch.Generator().manual_seed(seed))
    return F.interpolate(coarse, size=(size, size), mode="bilinear", align_corners=False)


# -- an independent reference: open_clip called directly ----------------------------------------------


def reference_images(model, images_B3HW):
    """CLIP image embeddings written out here: bicubic resize to the tower's 64 px, OpenAI normalisation,
    encode_image, L2 normalisation."""
    from open_clip.constants import OPENAI_DATASET_MEAN, OPENAI_DATASET_STD

    resized = F.interpolate(images_B3HW, size=(64, 64), mode="bicubic", antialias=True, align_corners=False)
    mean = torch.tensor(OPENAI_DATASET_MEAN)[:, None, None]
    std = torch.tensor(OPENAI_DATASET_STD)[:, None, None]
    with torch.no_grad():
        return F.normalize(model.encode_image((resized.clamp(0, 1) - mean) / std), dim=-1)


def reference_texts(model, texts):
    """CLIP text embeddings through open_clip's own tokenizer and encode_text, L2-normalised."""
    import open_clip

    with torch.no_grad():
        return F.normalize(model.encode_text(open_clip.get_tokenizer("ViT-S-32")(list(texts))), dim=-1)


def reference_scores(images_BE, conditions_BE, condition_keys):
    """Mean cosine with the own condition, and the share of images whose own condition is the nearest of
    the distinct ones (by an explicit loop)."""
    distinct = list(dict.fromkeys(condition_keys))
    representative = {key: conditions_BE[condition_keys.index(key)] for key in distinct}
    hits = 0
    for image_E, key in zip(images_BE, condition_keys):
        similarities = [float(image_E @ representative[other]) for other in distinct]
        hits += distinct[similarities.index(max(similarities))] == key
    return float((images_BE * conditions_BE).sum(dim=1).mean()), hits / len(condition_keys)


# -- the score ------------------------------------------------------------------------------------------


def test_an_image_scored_against_itself_as_its_tactile_condition_scores_one(metric):
    images = smooth_images(4, seed=1)
    scores = metric.condition_scores({"": images}, images, "tactile_source", digits=None)
    assert scores["clip_score"] == pytest.approx(1.0, abs=1e-5) and scores["clip_top1"] == 1.0
    metric.reset()
    metric.update(images, images)  # the pair form: the second image is the (tactile) condition
    assert metric.compute() == pytest.approx(1.0, abs=1e-5)


def test_the_pair_form_is_symmetric_and_bounded(metric):
    first, second = smooth_images(6, seed=2), smooth_images(6, seed=3)
    forward, backward = metric.per_image(first, second), metric.per_image(second, first)
    assert torch.allclose(forward, backward, atol=1e-6)
    assert bool(((forward >= -1) & (forward <= 1)).all()) and float(forward.max()) < 1 - 1e-4


@pytest.mark.parametrize("kind", ["label", "text", "visual"])
def test_scores_agree_with_open_clip_called_directly(tiny_clip, kind):
    """clip_score and clip_top1 of the generated images and of a repeated (background) image, against
    an independent computation: label prompts from the prompt option, texts as given, visual images."""
    path, model = tiny_clip
    prompt = "{label} pressed into a gel"
    metric = HOST.build("metric", options(path, prompt=prompt))
    generated = smooth_images(5, seed=4)
    background = generated[:1].expand_as(generated)
    if kind == "label":
        condition, keys = (
            torch.tensor([0, 2, 1, 2, 0]),
            [f"{name} pressed into a gel" for name in ("sphere", "ridge", "edge", "ridge", "sphere")],
        )
        conditions_BE = reference_texts(model, keys)
    elif kind == "text":
        condition = keys = ["a round bump", "a sharp edge", "a round bump", "three dots", "a flat press"]
        conditions_BE = reference_texts(model, keys)
    else:
        condition = smooth_images(5, seed=6)
        keys = list(range(5))
        conditions_BE = reference_images(model, condition)
    scores = metric.condition_scores(
        {"": generated, "background_": background}, condition, kind, CLASS_NAMES, digits=None
    )
    for prefix, images in (("", generated), ("background_", background)):
        expected_score, expected_top1 = reference_scores(reference_images(model, images), conditions_BE, keys)
        assert scores[f"{prefix}clip_score"] == pytest.approx(expected_score, abs=1e-5)
        assert scores[f"{prefix}clip_top1"] == pytest.approx(expected_top1)


def test_one_distinct_condition_gives_no_retrieval_figure(metric):
    """Matching an image to its condition among one condition is always right: no clip_top1 then."""
    scores = metric.condition_scores({"": smooth_images(3, seed=7)}, torch.tensor([1, 1, 1]), "label", CLASS_NAMES)
    assert "clip_score" in scores and "clip_top1" not in scores


@pytest.mark.parametrize(
    "key, condition, class_names, reason",
    [
        ("label", torch.tensor([0, -1]), CLASS_NAMES, "label -1 is not a class of this dataset"),
        ("label", torch.tensor([0, 1]), [], "need the dataset's class names"),
        ("text", ["a round bump", " "], [], "are empty texts"),
        ("depth_mm", torch.rand(2, 32, 32), [], "conditions read from samples' 'depth_mm' cannot be embedded by CLIP"),
    ],
)
def test_conditions_clip_cannot_embed_are_skipped_with_the_reason(metric, key, condition, class_names, reason):
    scores = metric.condition_scores({"": smooth_images(2, seed=8)}, condition, key, class_names)
    assert list(scores) == ["skipped"] and reason in scores["skipped"]["clip_score"]
    assert "\n" not in scores["skipped"]["clip_score"]


# -- weights: found, missing, wrong -------------------------------------------------------------------


def test_without_weights_the_metric_is_skipped_naming_the_file_and_where_to_put_it(monkeypatch):
    monkeypatch.delenv("VQTOUCH_CLIP_CKPT", raising=False)
    monkeypatch.delenv("VQTOUCH_WEIGHTS_DIR", raising=False)
    skipped = HOST.build("metric", "clip_score")
    assert isinstance(skipped, SkippedMetric) and "\n" not in skipped.skipped
    for needle in (
        "metric 'clip_score'",
        "open_clip_model.safetensors",
        "--clip-checkpoint",
        "VQTOUCH_CLIP_CKPT",
        "VQTOUCH_WEIGHTS_DIR",
        "never downloads",
    ):
        assert needle in skipped.skipped, needle
    assert MetricSet({"clip_score": skipped}).scores() == {"skipped": {"clip_score": skipped.skipped}}


def test_the_weights_are_found_through_the_environment_variable(monkeypatch, tiny_clip):
    monkeypatch.setenv("VQTOUCH_CLIP_CKPT", str(tiny_clip[0]))
    metric = HOST.build("metric", {k: v for k, v in options(tiny_clip[0]).items() if k != "checkpoint"})
    assert metric.skipped is None
    images = smooth_images(2, seed=9)
    assert metric.condition_scores({"": images}, images, "visual")["clip_score"] == pytest.approx(1.0, abs=1e-4)


def _write_other_weights(path):
    from safetensors.torch import save_file

    save_file({"not_clip": torch.zeros(1)}, str(path))


@pytest.mark.parametrize(
    "filename, write, reason",
    [
        ("absent.safetensors", None, "does not exist"),
        ("other.safetensors", _write_other_weights, "does not hold ViT-S-32 weights"),
        (
            "garbage.safetensors",
            lambda path: path.write_bytes(b"not a safetensors file" * 8),
            "does not hold ViT-S-32 weights",
        ),
        ("garbage.pt", lambda path: path.write_bytes(b"not a tensor pickle" * 8), "does not hold ViT-S-32 weights"),
    ],
)
def test_a_missing_or_wrong_weights_file_is_skipped_naming_it(tmp_path, filename, write, reason):
    pytest.importorskip("open_clip")
    path = tmp_path / filename
    if write is not None:
        write(path)
    skipped = HOST.build("metric", options(path))
    assert isinstance(skipped, SkippedMetric)
    assert str(path) in skipped.skipped and reason in skipped.skipped and "\n" not in skipped.skipped


def test_without_open_clip_the_metric_is_skipped_naming_the_extra(monkeypatch, tiny_clip):
    monkeypatch.setitem(sys.modules, "open_clip", None)  # makes `import open_clip` raise ModuleNotFoundError
    skipped = HOST.build("metric", options(tiny_clip[0]))
    assert skipped.skipped == "metric 'clip_score' needs open_clip_torch: pip install 'vqtouch[clip]'"


@pytest.mark.parametrize(
    "more, pattern",
    [
        (
            {"architecture": "ViT-S-33"},
            "metric 'clip_score': unknown open_clip architecture 'ViT-S-33'.*did you mean 'ViT-S-32'",
        ),
        ({"prompt": "a tactile image"}, r"must contain \{label\} exactly once"),
        ({"prompt": "{label} on {sensor}"}, r"must contain \{label\} exactly once"),
        ({"prompt": "{label"}, "is not a format string"),
    ],
)
def test_bad_options_are_one_line_config_errors(tiny_clip, more, pattern):
    with pytest.raises(ConfigError, match=pattern) as info:
        HOST.build("metric", options(tiny_clip[0], **more))
    assert "\n" not in str(info.value)


# -- generation scoring: the generator stage and `vqtouch evaluate generation` -------------------------


@pytest.fixture(scope="module")
def trained(tmp_path_factory, tiny_clip):
    """A tiny label-to-touch run (tokenizer 2 steps, generator 6) whose metrics include clip_score."""
    out = tmp_path_factory.mktemp("l2t") / "run"
    metrics = [{"name": "psnr"}, options(tiny_clip[0])]
    assert main(train_args(out, f"metrics={json.dumps(metrics)}")) == 0
    return out


def _evaluate(run, capsys, *flags):
    capsys.readouterr()
    status = main(
        ["evaluate", "generation", "--run", str(run), "--n", "4", "--steps", "2", "--no-distribution", *flags]
    )
    out, err = capsys.readouterr()
    return status, (json.loads(out) if status == 0 else err)


def test_the_generator_stage_scores_clip_score_beside_its_comparisons(trained):
    result = json.loads((trained / "generation.json").read_text())
    for prefix in ("", "real_", "background_", "ceiling_", "retrieval_", "class_mean_"):
        assert -1 <= result[f"{prefix}clip_score"] <= 1, prefix
        assert 0 <= result[f"{prefix}clip_top1"] <= 1, prefix
    assert "clip_score" not in result.get("skipped", {}) and 0 < result["psnr"] < 100


def test_evaluate_generation_scores_the_real_images_as_open_clip_does(trained, tiny_clip, capsys):
    """The run's own clip_score options (its checkpoint) are used; real_clip_score, which no generator
    changes, is the held-out ground truth against its label prompts computed directly."""
    from vqtouch.core import Assembly
    from vqtouch.plugins.runtime.run_dir import RunDir
    from vqtouch.plugins.utils.splits import split_dataset

    status, result = _evaluate(trained, capsys)
    assert status == 0, result
    config = RunDir.open(trained).load_config(HOST)
    dataset = Assembly(config, HOST).component("data.dataset")
    held_out = split_dataset(dataset, config.data.val_fraction, config.seed)[1]
    samples = [dataset[held_out.indices[i]] for i in range(4)]
    prompts = [f"a tactile sensor image of {dataset.class_names[sample['label']]}" for sample in samples]
    model = tiny_clip[1]
    expected, _ = reference_scores(
        reference_images(model, torch.stack([s["tactile"] for s in samples])), reference_texts(model, prompts), prompts
    )
    assert result["real_clip_score"] == pytest.approx(expected, abs=1e-4)
    assert "clip_score" in result and "clip_score" not in result.get("skipped", {})


def test_evaluate_generation_without_clip_weights_says_clip_score_is_skipped(trained, capsys, monkeypatch):
    monkeypatch.delenv("VQTOUCH_CLIP_CKPT", raising=False)
    status, result = _evaluate(trained, capsys, "--metrics", "psnr,clip_score")
    assert status == 0 and "VQTOUCH_CLIP_CKPT" in result["skipped"]["clip_score"] and "clip_score" not in result
    assert "psnr" in result and "background_psnr" in result


def test_evaluate_generation_takes_clip_weights_from_its_flags(trained, tiny_clip, capsys):
    block = json.dumps(["psnr", {"name": "clip_score", "model_overrides": TINY_RANDOM_CLIP}])
    status, result = _evaluate(
        trained, capsys, "--metrics", block, "--clip-checkpoint", str(tiny_clip[0]), "--clip-architecture", "ViT-S-32"
    )
    assert status == 0 and "psnr" in result and "skipped" not in result
    assert -1 <= result["clip_score"] <= 1 and -1 <= result["background_clip_score"] <= 1
    status, err = _evaluate(trained, capsys, "--clip-checkpoint", str(tiny_clip[0].with_name("absent.pt")))
    assert status == 2 and err.count("\n") == 1 and "--clip-checkpoint" in err and "no such file" in err


def test_score_generation_lists_conditions_clip_cannot_read_as_skipped(trained, tiny_clip):
    """Held-out label conditions without class names (a caller that built them without the dataset's):
    clip_score is skipped with the reason, beside the pair metrics' own skipped ones and scores."""
    from dataclasses import replace

    from vqtouch.core import Assembly
    from vqtouch.plugins.runtime.run_dir import RunDir
    from vqtouch.plugins.utils.splits import split_dataset
    from vqtouch.plugins.generator import load_pipeline
    from vqtouch.plugins.generator.scoring import held_out_conditions, score_generation

    pipe = load_pipeline(trained, host=HOST)
    config = RunDir.open(trained).load_config(HOST)
    dataset = Assembly(config, HOST).component("data.dataset")
    held_out = split_dataset(dataset, config.data.val_fraction, config.seed)[1]
    conditions = replace(held_out_conditions(held_out, dataset, 2, pipe.device), class_names=[])
    metrics = [
        ("psnr", HOST.build("metric", "psnr")),
        ("lpips", HOST.build("metric", "lpips")),  # no weights: skipped
        ("clip_score", HOST.build("metric", options(tiny_clip[0]))),
    ]
    scores = score_generation(
        generator=pipe.generator,
        conditioner=pipe.conditioners[0],
        tokenizer=pipe.tokenizer,
        sampler=HOST.build("sampler", "posterior"),
        conditions=conditions,
        metrics=metrics,
        background_3HW=None,
        steps=2,
        guidance=1.0,
        truncation=1.0,
        seed=0,
        device=pipe.device,
    )
    assert set(scores["skipped"]) == {"lpips", "clip_score"} and "class names" in scores["skipped"]["clip_score"]
    assert "psnr" in scores and not any("clip" in key for key in scores if key != "skipped")

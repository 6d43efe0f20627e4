"""Report verdicts that mean something: a green "better" needs a gap to the
strongest baseline that clears a stated minimum and the held-out images' noise, from a model whose
outputs follow its input.  The scores come from :class:`ContactRegionScores`; the verdict from the
report."""

import html
from pathlib import Path

import pytest
import torch

from vqtouch.plugins.evaluation.contact import (
    INPUT_CORRELATION_KEY,
    OUTPUT_SPREAD_KEY,
    ContactRegionScores,
    gap_interval_key,
    psnr_gap_interval,
)
from vqtouch.plugins.report.demo import UNCLEAR_MARK, _markdown_result
from vqtouch.plugins.report.html import render_html
from vqtouch.plugins.report.verdicts import contact_verdict


def stage_page(result: dict) -> str:
    report = {"scene": "label-to-touch", "stages": [{"stage": "generator", "status": "ran (1 s)", "result": result}]}
    return render_html(report, Path("/nonexistent-run"))


def presses(count=24, size=32, seed=0):
    """A flat grey background and ``count`` images of a bright square press at random places."""
    generator = torch.Generator().manual_seed(seed)
    background = torch.full((1, 3, size, size), 0.5)
    truth = background.repeat(count, 1, 1, 1)
    for image in truth:
        row, col = torch.randint(0, size - 10, (2,), generator=generator).tolist()
        image[:, row : row + 10, col : col + 10] += 0.3
    return truth, background


def scores_of(model, truth, background, **others):
    accumulated = ContactRegionScores(background)
    accumulated.update({"": model, "background_": background.expand_as(truth), **others}, truth)
    return accumulated.scores()


def test_the_gap_interval_has_closed_forms():
    errors = [3.0, 1.0, 0.5, 2.0, 8.0]
    values = [10, 20, 5, 40, 1]
    assert psnr_gap_interval(errors, errors, values) == (0.0, 0.0)
    # Ten times less squared error on every image: exactly 10 dB in every resample.
    low, high = psnr_gap_interval([e / 10 for e in errors], errors, values)
    assert low == pytest.approx(10.0) and high == pytest.approx(10.0)
    # Better on some images, worse on others: the interval straddles the pooled gap.
    low, high = psnr_gap_interval([1.0, 4.0, 0.2, 6.0, 1.0], errors, values)
    assert low < 0 < high


def test_the_output_spread_is_zero_for_a_constant_model_and_one_for_the_truth():
    truth, background = presses()
    constant = scores_of(truth.mean(0, keepdim=True).expand_as(truth), truth, background)
    assert constant[OUTPUT_SPREAD_KEY] == 0 and constant[INPUT_CORRELATION_KEY] == 0
    itself = scores_of(truth, truth, background)
    assert itself[OUTPUT_SPREAD_KEY] == 1 and itself[INPUT_CORRELATION_KEY] == 1
    half = scores_of(0.5 * truth + 0.25, truth, background)  # an affine copy: half the spread, all the input
    assert half[OUTPUT_SPREAD_KEY] == pytest.approx(0.5, abs=1e-4) and half[INPUT_CORRELATION_KEY] == 1
    inverted = scores_of(1 - truth, truth, background)
    assert inverted[INPUT_CORRELATION_KEY] == -1


def test_an_output_unrelated_to_its_input_gets_no_green_box():
    """Another image of the set each time: as varied as the truths and uncorrelated with them
    (``input_correlation`` says so, as a fact: a label-conditioned generator, which must invent the
    pose, is near 0 too, so it is no verdict rule); the strongest-baseline rule denies it the box."""
    truth, background = presses(count=48)
    scores = scores_of(truth.roll(1, dims=0), truth, background)
    assert scores[OUTPUT_SPREAD_KEY] == 1 and abs(scores[INPUT_CORRELATION_KEY]) < 0.05
    better, sentence = contact_verdict(scores)
    assert not better and "the no-contact background" in sentence


def test_a_constant_output_model_gets_no_green_box_even_when_it_beats_the_background():
    truth, background = presses()
    constant = truth.mean(0, keepdim=True).expand_as(truth)  # a faint smear of every press
    scores = scores_of(constant, truth, background)
    assert scores["contact_psnr"] > scores["background_contact_psnr"]
    better, sentence = contact_verdict(scores)
    assert not better and sentence.startswith("The model ignores its input: its outputs vary across inputs 0%")
    page = stage_page(scores)
    assert 'class="verdict worse"' in page and 'class="verdict better"' not in page
    assert 'class="num unclear"' in page and 'class="num better"' not in page


def test_a_genuinely_better_model_gets_its_green_box():
    truth, background = presses()
    noisy = (truth + 0.02 * torch.randn(truth.shape, generator=torch.Generator().manual_seed(1))).clamp(0, 1)
    scores = scores_of(noisy, truth, background)
    assert scores[gap_interval_key("background_", "low")] > 10
    better, sentence = contact_verdict(scores)
    assert better and "better than the no-contact background" in sentence and "95% interval" in sentence
    page = stage_page(scores)
    assert 'class="verdict better"' in page and 'class="num better"' in page


def test_a_gap_under_the_minimum_or_within_the_noise_is_no_better():
    # The demo's 40-step tokenizer: 0.07 dB over the background.
    tiny = {"contact_fraction": 0.3, "contact_psnr": 25.34, "background_contact_psnr": 25.27}
    better, sentence = contact_verdict(tiny)
    assert not better
    assert "no better than the no-contact background within noise" in sentence and "0.5 dB minimum" in sentence
    markdown = "\n".join(_markdown_result({**tiny, "psnr": 25.0, "background_psnr": 24.0}, "t"))
    assert f"25 {UNCLEAR_MARK}" in markdown and "✓" not in markdown.split("\n\n*")[0]
    # A large mean gap that other held-out images could erase.
    noisy = {
        "contact_psnr": 27.0,
        "background_contact_psnr": 25.0,
        gap_interval_key("background_", "low"): -0.4,
        gap_interval_key("background_", "high"): 4.1,
    }
    better, sentence = contact_verdict(noisy)
    assert not better and "another draw of held-out images could bring the gap under" in sentence
    assert "-0.40 to +4.10" in sentence
    # The demo's 40-step tokenizer, as `evaluate reconstruction --run runs/demo` scored it: 0.65 dB over
    # the background, but the interval's low end is 0.08 dB, under the 0.5 dB minimum.
    demo = {
        "contact_fraction": 0.27,
        "contact_psnr": 25.9237,
        "background_contact_psnr": 25.2733,
        "output_spread_ratio": 0.7331,
        "input_correlation": 0.344,
        gap_interval_key("background_", "low"): 0.0766,
        gap_interval_key("background_", "high"): 1.2,
    }
    better, sentence = contact_verdict(demo)
    assert not better and sentence.startswith("On the contact region (27% of pixels) the model is no better than")


def test_the_strongest_baseline_decides():
    # The bundled generator beat the background but lost to the class-mean image.
    result = {
        "contact_psnr": 26.33,
        "background_contact_psnr": 25.0,
        "class_mean_contact_psnr": 27.49,
        "ceiling_contact_psnr": 33.0,  # a ceiling is no baseline
    }
    better, sentence = contact_verdict(result)
    assert not better
    assert (
        "worse than the class-mean training image (the strongest baseline here): contact PSNR 26.33 vs 27.49"
        in sentence
    )


def test_stages_trained_for_the_demos_length_carry_the_caveat_at_their_top(make_plugin):
    from vqtouch.core import PluginError, hookimpl, load_plugins
    from vqtouch.core.config import resolve_config, scale_for_demo
    from vqtouch.plugins.report.demo import brief_training_caveat, render_report

    host = load_plugins(autoload=False)
    scene = resolve_config("tour", (), (), host=host)
    scaled = scale_for_demo(scene, host)
    caveats = {stage: brief_training_caveat(stage, scaled, host) for stage in scaled.stages}
    assert {stage for stage, caveat in caveats.items() if caveat} == {"tokenizer", "adapt", "generator", "fewshot"}
    assert caveats["tokenizer"].startswith("Trained for 40 steps (tokenizer.train.steps), the demo's length")
    assert not any(brief_training_caveat(stage, scene, host) for stage in scene.stages)  # --full

    entry = {"stage": "tokenizer", "status": "ran (1 s)", "caveat": caveats["tokenizer"], "result": {"psnr": 1.0}}
    report = {"scene": "tour", "run_dir": "/x", "stages": [entry], "components": []}
    page = render_html(report, Path("/x"))
    assert f'<p class="caveat"><b>Trained briefly.</b> {html.escape(caveats["tokenizer"])}</p>' in page
    assert f"> **Trained briefly.** {caveats['tokenizer']}" in render_report(report)

    @hookimpl
    def vqtouch_register_stages(register):
        register("odd", lambda job: None, demo={"steps": 3}, trains="train.steps")

    with pytest.raises(PluginError, match="trains 'train.steps' but its demo caps do not name it"):
        load_plugins(autoload=False, extra=[make_plugin("odd_stage", vqtouch_register_stages)])


def test_report_md_gives_a_skip_reason_once_however_many_stages_and_components_skip_it():
    from vqtouch.plugins.report.demo import render_report

    reason = ("metric 'lpips' needs vgg16-397923af.pth;" + " put it in VQTOUCH_WEIGHTS_DIR." * 10).strip()
    stages = [
        {"stage": name, "status": "ran (1 s)", "result": {"psnr": 1.0, "skipped": {"lpips": reason}}}
        for name in ("tokenizer", "generator", "pretrained")
    ]
    components = [{"slot": "metrics[3]", "plugin": "lpips", "status": f"skipped: {reason}"}]
    report = {"scene": "tour", "run_dir": "/x", "stages": stages, "components": components}
    markdown = render_report(report)
    assert markdown.count(reason) == 1
    assert "- **lpips** (stage tokenizer, stage generator, stage pretrained, component metrics[3])" in markdown
    assert markdown.count("skipped lpips (reasons under Skipped)") == 3
    assert render_html(report, Path("/x")).count(html.escape(reason)) == 1


def test_the_held_out_loss_has_an_axis_of_its_own():
    from vqtouch.plugins.report.html import loss_figure, loss_plot

    curves = {"loss": [(1, 5.0), (10, 3.0), (20, 2.0)], "val_loss": [(10, 0.4), (20, 0.3)]}
    figure = loss_figure(curves, "t")
    train_axis, held_out_axis = figure.axes
    assert train_axis.get_ylabel() == "training loss" and held_out_axis.get_ylabel() == "held-out val_loss"
    assert [line.get_ydata().tolist() for line in held_out_axis.get_lines()] == [[0.4, 0.3]]
    assert [line.get_ydata().tolist() for line in train_axis.get_lines()] == [[5.0, 3.0, 2.0]]
    assert len(loss_figure({"loss": curves["loss"]}, "t").axes) == 1
    assert loss_plot(curves, "t").startswith(b"\x89PNG") and loss_plot({"loss": [(1, 1.0)]}, "t") is None


def test_a_briefly_trained_tokenizer_gets_no_green_box(tmp_path):
    """End to end: a tokenizer trained 2 steps draws about the same blob for every input; its stage's
    scores carry the evidence and the report's verdict is not green."""
    import json

    from generator_runs import TINY_TOKENIZER
    from vqtouch.core import Assembly, load_plugins, resolve_config
    from vqtouch.plugins.runtime.execution import run_stage
    from vqtouch.plugins.runtime.run_dir import RunDir

    host = load_plugins(autoload=False)
    overrides = [*TINY_TOKENIZER, 'stages=["tokenizer"]', 'metrics=[{"name": "psnr"}]', "data.val_fraction=0.25"]
    config = resolve_config("reconstruction", host=host, overrides=overrides)
    run = RunDir.create(config, host=host, path=tmp_path / "run")
    assert run_stage("tokenizer", Assembly(config, host), run).status == "ran"
    scores = json.loads((run.path / "eval.json").read_text())
    assert {OUTPUT_SPREAD_KEY, INPUT_CORRELATION_KEY, gap_interval_key("background_", "low")} <= set(scores)
    better, sentence = contact_verdict(scores)
    assert not better, sentence

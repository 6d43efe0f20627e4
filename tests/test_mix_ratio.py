"""`vqtouch evaluate mix-ratio` at toy size: what each arm's trainer received (images and steps under
both budgets), the resume of an interrupted run, the zero-shot and background rows against
independent recomputations, the best-setting and verdict rules on hand-made summaries, the
refusals and the files the command writes."""

import json

import pytest
import torch
from cli_checks import snapshot

from vqtouch.core import ConfigError, load_plugins
from vqtouch.plugins.cli.app import main
from vqtouch.plugins.adaptation.adapt_images import family_images, target_images
from vqtouch.plugins.adaptation.families import load_families
from vqtouch.plugins.adaptation.fewshot import BACKGROUND, SHOTS_ALONE, ZERO_SHOT
from vqtouch.plugins.adaptation.ratio import (
    ALL_IMAGES,
    EXPOSURES,
    STEPS,
    best_settings,
    check_ratios,
    evaluate_mix_ratio,
    exposure_steps,
    verdict_lines,
)
from vqtouch.plugins.scenes import GELSIGHT_DERIVATIVE_II

HOST = load_plugins(autoload=False)
TARGET = json.dumps(GELSIGHT_DERIVATIVE_II)


def _metric(name, predicted, truth):
    metric = HOST.build("metric", {"name": name})
    metric.update(predicted, truth)
    return float(metric.compute())


def _run(family_tokenizer_run, family_clusters, out, **overrides):
    settings = dict(
        target=TARGET,
        seeds=[0],
        shots=4,
        ratios=(0, 1, 2),
        steps=2,
        all_images=8,
        eval_images=4,
        families=family_clusters,
        cost_controls=(2,),
        report=lambda line: None,
    )
    return evaluate_mix_ratio(family_tokenizer_run, HOST, out, **(settings | overrides))


def test_every_arm_trains_its_mix_for_its_budget_and_an_interrupted_run_resumes(
    family_tokenizer_run, family_clusters, tokenizer_trainer_calls, tmp_path
):
    out = tmp_path / "ratio"
    result = _run(family_tokenizer_run, family_clusters, out)
    rows = {row["arm"]: row for row in result["rows"]}
    assert set(rows) == {
        ZERO_SHOT,
        BACKGROUND,
        SHOTS_ALONE,
        "mixed 1:1, equal steps",
        "mixed 1:2, equal steps",
        "mixed 1:1, equal exposures",
        "mixed 1:2, equal exposures",
        "shots alone, 6 steps",
        ALL_IMAGES,
    }
    # Each trainer got its arm's images and steps: the shots (then ratio x shots family images) for 2
    # steps at equal steps and 2 x (1 + ratio) at equal exposures; the shots alone for as long as the 1:2
    # mix at equal exposures (the cost control); all images alone for 2 steps.
    families = load_families(family_clusters, HOST)
    family = result["assignments"][0]["family"]
    _, source, shots, _ = target_images(TARGET, HOST, shots=4, eval_images=4, image_size=32, seed=0)
    _, _, everything, _ = target_images(TARGET, HOST, shots=8, eval_images=4, image_size=32, seed=0)
    expected = [(shots, 2), (everything, 2), (shots, 6)]
    for ratio in (1, 2):
        family_N, _ = family_images(families, family, HOST, count=4 * ratio, image_size=32, seed=0, exclude=source)
        expected += [(torch.cat([shots, family_N]), 2), (torch.cat([shots, family_N]), 2 * (1 + ratio))]
    assert len(tokenizer_trainer_calls) == len(expected) == 7
    for images, steps in expected:
        matches = [
            call
            for call in tokenizer_trainer_calls
            if call["steps"] == steps and call["images"].shape == images.shape and torch.equal(call["images"], images)
        ]
        assert len(matches) == 1, (len(images), steps)
    # Equal exposures: every arm sees as many sensor images as the shots alone (batch 4: the 4 shots).
    assert rows[SHOTS_ALONE]["target_views"] == 2 * 4
    assert rows["mixed 1:2, equal exposures"]["target_views"] == 2 * 4
    assert rows["mixed 1:2, equal steps"]["target_views"] == round(2 * 4 / 3)
    assert rows["mixed 1:2, equal exposures"]["steps"] == 6 and rows[ALL_IMAGES]["train_images"] == 8

    # Zero-shot: the unchanged tokenizer on the held-out images; the background: the sensor's no-contact
    # image scored directly on them.
    from vqtouch.plugins.evaluation.contact import no_contact_image
    from vqtouch.plugins.tokenizer import load_tokenizer, reconstruct_all

    tokenizer, _ = load_tokenizer(family_tokenizer_run, HOST)
    _, _, _, held_out = target_images(TARGET, HOST, shots=4, eval_images=4, image_size=32, seed=0)
    assert rows[ZERO_SHOT]["ssim"] == pytest.approx(
        _metric("ssim", reconstruct_all(tokenizer, held_out), held_out), abs=1e-4
    )
    background = no_contact_image(HOST.build("sensor_family", GELSIGHT_DERIVATIVE_II), held_out)
    assert rows[BACKGROUND]["psnr"] == pytest.approx(_metric("psnr", background, held_out), abs=1e-4)

    # Interrupted before its record: the run again reads every finished arm back and trains none.
    (out / "mix_ratio.json").unlink()
    tokenizer_trainer_calls.clear()
    again = _run(family_tokenizer_run, family_clusters, out)
    assert tokenizer_trainer_calls == []
    assert again["rows"] == result["rows"]
    # An arm trained with other settings is not this run's: refused, naming them; --overwrite trains again.
    (out / "mix_ratio.json").unlink()
    finished = snapshot(out)
    with pytest.raises(
        ConfigError, match=r"holds a finished arm with other settings: steps 2 \(now 3\); pass --overwrite"
    ):
        _run(family_tokenizer_run, family_clusters, out, steps=3)
    assert snapshot(out) == finished and tokenizer_trainer_calls == []
    again = _run(family_tokenizer_run, family_clusters, out, steps=3, overwrite=True)
    assert sorted(call["steps"] for call in tokenizer_trainer_calls) == [3, 3, 3, 3, 6, 9, 9]


def _summary(**ssim):
    """A hand-made mean_spread summary: zero-shot, the shots alone, two mixes per budget, all images."""
    rows = [
        {"arm": ZERO_SHOT, "budget": "-", "ratio": 0.0, "ssim": 0.80, "family_psnr": 28.0, "steps": 0},
        {"arm": SHOTS_ALONE, "budget": "both", "ratio": 0.0, "ssim": ssim["shots"], "family_psnr": 24.0, "steps": 200},
        {"arm": ALL_IMAGES, "budget": "-", "ratio": 0.0, "ssim": ssim["all"], "family_psnr": 24.0, "steps": 200},
    ]
    for budget in (STEPS, EXPOSURES):
        for ratio, family_psnr in ((1.0, 27.0), (5.0, 31.0)):
            rows.append(
                {
                    "arm": f"mixed 1:{ratio:g}, {budget}",
                    "budget": budget,
                    "ratio": ratio,
                    "ssim": ssim[f"{budget}{ratio:g}"],
                    "ssim_std": 0.001,
                    "family_psnr": family_psnr,
                    "steps": 200 if budget == STEPS else 200 * (1 + int(ratio)),
                }
            )
    return rows


def test_the_best_settings_and_the_targets_verdicts_follow_the_numbers():
    summary = _summary(
        shots=0.870,
        all=0.880,
        **{f"{STEPS}1": 0.850, f"{STEPS}5": 0.820, f"{EXPOSURES}1": 0.875, f"{EXPOSURES}5": 0.865},
    )
    best = best_settings(summary)
    assert best[STEPS] == {"ratio": 0.0, "ssim": 0.870, "keeps_family": {"ratio": 5.0, "ssim": 0.820}}
    assert best[EXPOSURES] == {"ratio": 1.0, "ssim": 0.875, "keeps_family": {"ratio": 5.0, "ssim": 0.865}}
    lines = verdict_lines(summary)
    assert "mixed 1:1, equal exposures, is 0.005 ssim below all images" in lines[0] and lines[0].endswith(": met.")
    assert "beats shots alone by 0.005" in lines[1]
    worse = _summary(
        shots=0.870,
        all=0.900,
        **{f"{STEPS}1": 0.850, f"{STEPS}5": 0.820, f"{EXPOSURES}1": 0.860, f"{EXPOSURES}5": 0.865},
    )
    lines = verdict_lines(worse)
    assert "is 0.035 ssim below all images" in lines[0] and lines[0].endswith(": missed.")
    above = _summary(
        shots=0.870,
        all=0.860,
        **{f"{STEPS}1": 0.850, f"{STEPS}5": 0.820, f"{EXPOSURES}1": 0.875, f"{EXPOSURES}5": 0.865},
    )
    assert "is 0.015 ssim above all images" in verdict_lines(above)[0]
    assert "is behind shots alone" in lines[1]
    # Trained longer than the shots alone with no control as long: the verdicts say so.
    assert "part of its gain over the shots alone may be the longer training; `--cost-controls 5`" in lines[-1]
    control = {"arm": "shots alone, 1200 steps", "budget": "equal cost", "ratio": 0.0, "ssim": 0.90, "steps": 1200}
    lines = verdict_lines([*worse, control])
    assert "is behind shots alone, 1200 steps" in lines[2] and "--cost-controls" not in "".join(lines)


def test_exposure_steps_and_ratio_checks():
    assert [exposure_steps(200, r) for r in (0, 1, 2, 5, 10)] == [200, 400, 600, 1200, 2200]
    assert check_ratios([5, 0, 1]) == [0.0, 1.0, 5.0]
    for ratios, message in (
        ([0, 0], "repeats a ratio"),
        ([0], "add at least one ratio > 0"),
        ([1, float("inf")], "give finite ratios >= 0"),
        ([], "give finite ratios >= 0"),
    ):
        with pytest.raises(ConfigError, match=message):
            check_ratios(ratios)
    with pytest.raises(ConfigError, match=r"--cost-controls 3: name mix ratios of --ratios \(1 2\)"):
        evaluate_mix_ratio("nowhere", HOST, "nowhere", target=TARGET, seeds=[0], ratios=(0, 1, 2), cost_controls=(3, 1))


@pytest.mark.parametrize(
    "flags, message",
    [
        (["--ratios", "1", "1"], "--ratios 1 1 repeats a ratio"),
        (["--ratios", "0"], "--ratios 0: add at least one ratio > 0"),
        (["--seeds", "1", "1"], "--seeds 1 1 repeats a seed"),
        (["--ratios", "-1"], "--ratios"),
    ],
)
def test_bad_settings_get_one_line_errors(family_tokenizer_run, tmp_path, capsys, flags, message):
    assert (
        main(["evaluate", "mix-ratio", "--run", str(family_tokenizer_run), "--out", str(tmp_path / "x"), *flags]) == 2
    )
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and message in error
    assert not (tmp_path / "x").exists()


def test_a_folder_that_is_not_a_run_is_refused(family_tokenizer_run, tmp_path):
    step_folder = next((family_tokenizer_run / "checkpoints").iterdir())
    with pytest.raises(ConfigError, match="not a run directory"):
        evaluate_mix_ratio(step_folder, HOST, tmp_path / "x", target=TARGET, seeds=[0])


def test_the_command_writes_its_files_and_refuses_to_overwrite_them(
    family_tokenizer_run, family_clusters, tmp_path, capsys
):
    out = tmp_path / "ratio"
    args = ["--no-progress", "evaluate", "mix-ratio", "--run", str(family_tokenizer_run), "--out", str(out)]
    args += ["--shots", "4", "--ratios", "0", "2", "--steps", "1", "--all-images", "6", "--eval-images", "2"]
    args += ["--seeds", "3", "--families", str(family_clusters)]
    assert main(args) == 0
    printed = capsys.readouterr().out
    result = json.loads((out / "mix_ratio.json").read_text())
    assert result["experiment"] == "mix_ratio" and result["seeds"] == [3]
    assert (out / "mix_ratio.png").stat().st_size > 10_000
    assert "| mixed 1:2, equal exposures | equal exposures | 2.0 | 3 |" in printed
    assert f"-> {out} (mix_ratio.json, mix_ratio.md, mix_ratio.png" in printed
    before = (out / "mix_ratio.json").read_text()
    assert main(args) == 2
    assert f"{out} already holds a mix-ratio experiment; pass --overwrite" in capsys.readouterr().err
    assert (out / "mix_ratio.json").read_text() == before

"""The ``cluster`` and ``adapt`` stages in the few-shot, zero-shot and cross-sensor scenes:
every stage runs in a tiny demo, the adapt stage reuses the cluster stage's families (or clusters
without the unseen sensor itself), and the report shows both pictures."""

import json

import pytest

from generator_runs import TINY
from vqtouch.core import load_plugins, read_metadata
from vqtouch.plugins.cli.app import main

HOST = load_plugins(autoload=False)
#: Tiny stages; an untrained tokenizer's families are tight, so the thresholds are generous here
#: (refusals are tested in test_adapt.py).
TINY_ADAPTATION = [
    "cluster.images_per_sensor=4",
    "cluster.variants_per_family=1",
    "cluster.threshold=100",
    "adapt.steps=2",
    "adapt.shots=4",
    "adapt.eval_images=4",
    "adapt.threshold=100",
    "fewshot.generator_steps=2",
    "fewshot.samples=2",
    "fewshot.feature_size=32",
]


def _demo(out, scene, *extra):
    args = ["--no-progress", "demo", "--scene", scene, "--out", str(out)]
    tiny = [item for item in TINY if scene == "few-shot" or not item.startswith("generator.")]
    for override in [*tiny, *TINY_ADAPTATION, *extra]:
        args += ["--set", override]
    return main(args)


def _stages(out):
    return {stage["stage"]: stage for stage in json.loads((out / "report.json").read_text())["stages"]}


def test_the_few_shot_scene_clusters_assigns_adapts_and_generates(tmp_path, capsys):
    from vqtouch.plugins.generator import load_pipeline
    from vqtouch.plugins.tokenizer import load_tokenizer, tokenizer_digest

    out = tmp_path / "few"
    assert _demo(out, "few-shot") == 0
    assert "scene few-shot: 5 of 5 stages ran, 0 cannot run, 0 failed" in capsys.readouterr().out
    stages = _stages(out)
    clusters = json.loads((out / "cluster" / "cluster.json").read_text())
    # Every registered family and one variant of each; the unseen sensor is assigned, not clustered.
    assert stages["cluster"]["result"]["sensors"] == len(clusters["sensors"]) == 2 * 3
    assigned = clusters["assignments"]["gelsight/v1"]
    assert stages["cluster"]["result"]["target_family"] == assigned["family"] == stages["adapt"]["result"]["family"]
    assert 0 < stages["cluster"]["result"]["zero_shot_psnr"] < 100
    adapted = stages["adapt"]["result"]  # each score beside the family tokenizer's and the background's
    assert {"psnr", "before_psnr", "background_psnr", "contact_psnr", "background_contact_psnr"} <= set(adapted)
    assert not (out / "adapted" / "families").exists()  # the adapt stage reused the cluster stage's families
    header = read_metadata(out / "adapted" / "autoencoder.safetensors")
    assert header["adaptation.shots"] == "4" and header["adaptation.family"] == str(assigned["family"])
    load_tokenizer(out / "adapted", HOST)
    report = (out / "report.md").read_text()
    assert "![cluster](cluster/families.png)" in report and "![adapt](adapted/before_after.png)" in report
    assert (out / "cluster" / "families.png").is_file() and (out / "adapted" / "before_after.png").is_file()
    # The fewshot stage fine-tunes this run's generator for the target on the adapt stage's tokenizer.
    fewshot = stages["fewshot"]["result"]
    # It adapts the decoder alone (the adapt stage adapted the whole tokenizer): its own adapted tokenizer.
    assert fewshot["adapted_tokenizer"] == "adapted here" and fewshot["target"] == "gelsight/v1"
    assert fewshot["generator_steps"] == 2 and fewshot["shots"] == 4  # fewshot.generator_steps, adapt.shots
    assert json.loads((out / "fewshot" / "tokenizer" / "adapt.json").read_text())["part"] == "decoder"
    assert tokenizer_digest(out / "fewshot" / "tokenizer") != tokenizer_digest(out / "adapted")
    assert {"label_few_shot_fd_effnetlite0", "label_zero_shot_fd_effnetlite0", "label_few_shot_contact_psnr"} <= set(
        fewshot
    )
    assert "![fewshot](fewshot/samples.png)" in report and (out / "fewshot" / "samples.png").is_file()
    pipe = load_pipeline(out / "fewshot" / "generator", host=HOST)
    assert pipe.sensor_tag is not None and pipe(label=0, n=1, steps=2).shape == (1, 3, 32, 32)


def test_the_cross_sensor_scene_adapts_to_gelsight_mini_and_scores_its_real_frames(tmp_path, capsys):
    out = tmp_path / "cross"
    assert _demo(out, "cross-sensor") == 0
    assert "scene cross-sensor: 3 of 3 stages ran, 0 cannot run, 0 failed" in capsys.readouterr().out
    result = _stages(out)["adapt"]["result"]
    clusters = json.loads((out / "adapted" / "families" / "cluster.json").read_text())
    names = [sensor["name"] for sensor in clusters["sensors"]]
    # Without a cluster stage the adapt stage clusters the defaults itself, leaving the target out.
    assert "gelsight_mini" not in names and {"gelsight", "digit", "gelsight_mini/v101"} <= set(names)
    # ... and writes them with the target's assignment (the plot shows it as a star).
    assert clusters["assignments"]["gelsight_mini"]["family"] == _stages(out)["adapt"]["result"]["family"]
    assert (out / "adapted" / "families" / "families.png").is_file()
    summary = json.loads((out / "adapted" / "adapt.json").read_text())
    assert summary["real_frames"]["count"] == 24  # taxim's real GelSight Mini frames
    assert result["real_frames_ssim"] == summary["real_frames"]["after"]["ssim"]
    assert set(summary["members_used"]) <= set(clusters["families"][summary["family"]])


def test_the_zero_shot_scene_assigns_without_adapting(tmp_path, capsys):
    out = tmp_path / "zero"
    assert _demo(out, "zero-shot") == 0
    assert "scene zero-shot: 3 of 3 stages ran, 0 cannot run, 0 failed" in capsys.readouterr().out
    assert _stages(out)["cluster"]["result"]["target"] == "gelsight/v2"
    assert not (out / "adapted").exists()


@pytest.mark.parametrize("stage", ["cluster", "adapt"])
def test_without_a_trained_tokenizer_the_stages_say_so(tmp_path, capsys, stage):
    out = tmp_path / stage
    assert _demo(out, "few-shot", f'stages=["{stage}"]') == 0
    status = _stages(out)[stage]["status"]
    assert status.startswith("cannot run: no trained tokenizer in this run"), status

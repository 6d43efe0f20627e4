"""`vqtouch evaluate cross-sensor` end to end at toy size: every part's rows, the
summary's means and spreads against an independent recomputation, the arms' settings as written
by each adapted tokenizer, and the files (JSON, markdown, PNG)."""

import json
import statistics

import pytest

from generator_runs import tiny_tokenizer_args
from vqtouch.plugins.cli.app import main


@pytest.fixture(scope="module")
def tokenizer_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("xs") / "tok"
    assert main(tiny_tokenizer_args(out)) == 0
    return out


def test_cross_sensor_evaluation_writes_every_part(tokenizer_run, tmp_path, capsys):
    out = tmp_path / "eval"
    assert (
        main(
            [
                "--no-progress",
                "evaluate",
                "cross-sensor",
                "--run",
                str(tokenizer_run),
                "--out",
                str(out),
                "--seeds",
                "0",
                "1",
                "--steps",
                "1",
                "--shots",
                "2",
                "3",
                "--main-shots",
                "3",
                "--ratios",
                "1",
                "2",
                "--main-ratio",
                "2",
                "--everything",
                "4",
                "--eval-images",
                "2",
                "--variants",
                "2",
                "--held-out-variants",
                "1",
                "--images",
                "3",
                "--clusterers",
                "kmeans",
                "--real-shots",
                "2",
            ]
        )
        == 0
    )
    result = json.loads((out / "cross_sensor.json").read_text())
    recovery = result["family_recovery"]["rows"]
    assert [(row["clusterer"], row["seed"]) for row in recovery] == [("kmeans", 0), ("kmeans", 1)]
    assert all(-1 <= row["ari"] <= 1 and row["sensors"] == 3 * 3 and row["held_out_sensors"] == 3 for row in recovery)
    transfer = [row for row in result["transfer"]["rows"] if row["seed"] == 0]
    assert [(row["arm"][0], row["shots"], row["ratio"]) for row in transfer] == [
        ("a", 0, None),
        ("b", 2, 0.0),
        ("b", 3, 0.0),
        ("c", 2, 2.0),
        ("c", 3, 2.0),
        ("c", 3, 1.0),
        ("d", 4, 1.0),
    ]
    # Each arm's tokenizer says how it was made; the zero-shot row is the family tokenizer's "before".
    arm = json.loads((out / "arms" / "seed0" / "c-3-2" / "adapt.json").read_text())
    assert arm["shots"] == 3 and arm["family_images"] == 6 and arm["steps"] == 1 and arm["held_out"] == 2
    assert transfer[0]["ssim"] == arm["before"]["ssim"] and transfer[4]["ssim"] == arm["after"]["ssim"]
    assert transfer[4]["fd_effnetlite0"] == arm["after"]["fd_effnetlite0"] >= 0
    assert transfer[4]["family_ssim"] == arm["family_held_out"]["after"]["ssim"]
    assert transfer[0]["family_psnr"] == arm["family_held_out"]["before"]["psnr"]
    # The summary is the mean and spread over the seeds of the rows.
    rows = [
        row
        for row in result["transfer"]["rows"]
        if row["arm"].startswith("c") and row["shots"] == 3 and row["ratio"] == 2.0
    ]
    summary = next(
        row
        for row in result["transfer"]["summary"]
        if row["arm"].startswith("c") and row["shots"] == 3 and row["ratio"] == 2.0
    )
    assert summary["seeds"] == 2
    assert summary["psnr"] == pytest.approx(statistics.fmean(row["psnr"] for row in rows), abs=1e-4)
    assert summary["psnr_std"] == pytest.approx(statistics.pstdev(row["psnr"] for row in rows), abs=1e-4)
    real = result["real_frames"]["rows"]
    assert {row["arm"][0] for row in real} == {"a", "b", "c"} and all(row["held_out"] == 22 for row in real)
    for cost in result["cost"]["rows"]:
        assert cost["ratio"] == pytest.approx(cost["adaptation_seconds"] / cost["scratch_seconds"], rel=1e-3)
        assert cost["scratch_steps"] == 2
    markdown = (out / "cross_sensor.md").read_text()
    assert "## Family recovery" in markdown and "| c: mixed | 3 | 2.0 |" in markdown and "## Cost" in markdown
    assert (out / "cross_sensor.png").stat().st_size > 10_000
    assert "-> " + str(out) in capsys.readouterr().out


def test_main_shots_must_be_swept(tokenizer_run, tmp_path, capsys):
    assert (
        main(
            [
                "evaluate",
                "cross-sensor",
                "--run",
                str(tokenizer_run),
                "--out",
                str(tmp_path / "x"),
                "--shots",
                "2",
                "3",
                "--main-shots",
                "5",
            ]
        )
        == 2
    )
    assert "--main-shots 5 must be one of --shots [2, 3]" in capsys.readouterr().err

"""``vqtouch evaluate generation --out``: one generator per seed, every conditioner against the baselines."""

from __future__ import annotations

import json
import statistics

import pytest

from generator_runs import TINY
from vqtouch.plugins.cli.app import main
from vqtouch.plugins.generator.experiment import rows_of, score_keys, verdicts

CONDITIONERS = '[{"name": "label"}, {"name": "text_scratch", "width": 16, "depth": 1, "heads": 2, "vocab_buckets": 64}]'


def experiment_args(out, *extra):
    args = [
        "--no-progress",
        "evaluate",
        "generation",
        "--out",
        str(out),
        "--scene",
        "label-to-touch",
        "--seeds",
        "0",
        "1",
        "--n",
        "3",
        "--no-distribution",
        *extra,
    ]
    for override in [*TINY, f"generator.conditioners={CONDITIONERS}"]:
        args += ["--set", override]
    return args


@pytest.fixture(scope="module")
def experiment(tmp_path_factory):
    out = tmp_path_factory.mktemp("generation") / "exp"
    assert main(experiment_args(out)) == 0
    return out, json.loads((out / "generation.json").read_text())


def test_every_seed_trains_one_generator_over_one_tokenizer_and_scores_each_conditioner(experiment):
    out, result = experiment
    assert (out / "generation.md").is_file() and (out / "generation.png").stat().st_size > 0
    assert result["seeds"] == [0, 1] and result["n"] == 3
    for seed in (0, 1):
        config = json.loads((out / f"seed{seed}" / "config.json").read_text())
        assert config["seed"] == seed and config["generator"]["tokenizer_run"] == str((out / "tokenizer").resolve())
        generation = json.loads((out / f"seed{seed}" / "generation.json").read_text())
        for key, scores in generation["by_conditioner"].items():
            mine = next(
                row
                for row in result["rows"]
                if row["seed"] == seed and row["method"] == "generator" and row["conditioner"] == key.split(":")[1]
            )
            assert mine["psnr"] == scores["psnr"] and mine["contact_psnr"] == scores["contact_psnr"]
            background = next(
                row
                for row in result["rows"]
                if row["seed"] == seed
                and row["method"] == "no-contact image"
                and row["conditioner"] == key.split(":")[1]
            )
            assert background["psnr"] == scores["background_psnr"]
    generators = [row for row in result["rows"] if row["method"] == "generator"]
    assert sorted({row["conditioner"] for row in generators}) == ["label", "text_scratch"] and len(generators) == 4
    # Two seeds train two different generators: their samples differ.
    by_seed = {row["seed"]: row["psnr"] for row in generators if row["conditioner"] == "label"}
    assert by_seed[0] != by_seed[1]


def test_the_summary_is_the_mean_and_spread_of_the_rows(experiment):
    _, result = experiment
    for entry in result["summary"]:
        members = [
            row
            for row in result["rows"]
            if row["conditioner"] == entry["conditioner"] and row["method"] == entry["method"]
        ]
        assert entry["seeds"] == len(members) == 2
        assert entry["psnr"] == pytest.approx(statistics.fmean(row["psnr"] for row in members), abs=1e-6)
        assert entry["psnr_std"] == pytest.approx(statistics.pstdev(row["psnr"] for row in members), abs=1e-6)


def test_a_second_call_refuses_to_overwrite_and_run_only_flags_are_refused(experiment, tmp_path, capsys):
    out, _ = experiment
    assert main(experiment_args(out)) == 2
    assert "already holds a generation experiment; pass --overwrite" in capsys.readouterr().err
    assert main(experiment_args(tmp_path / "x", "--sampler", "purity")) == 2
    assert "--sampler only apply to scoring one run" in capsys.readouterr().err
    assert main(["evaluate", "generation", "--out", str(tmp_path / "y"), "--scene", "reconstruction"]) == 2
    assert "has no generator" in capsys.readouterr().err


def test_rows_strip_baseline_prefixes_and_leave_sampling_facts_out():
    scores = {
        "psnr": 20.0,
        "contact_psnr": 15.0,
        "background_psnr": 25.0,
        "background_contact_psnr": 14.0,
        "retrieval_psnr": 21.0,
        "samples": 8,
        "steps": 10,
        "contact_fraction": 0.2,
        "skipped": {},
    }
    assert score_keys(scores) == ["psnr", "contact_psnr"]
    rows = rows_of({"by_conditioner": {"0:label": scores}}, seed=3)
    assert rows[0] == {"conditioner": "label", "method": "generator", "seed": 3, "psnr": 20.0, "contact_psnr": 15.0}
    assert rows[1] == {
        "conditioner": "label",
        "method": "no-contact image",
        "seed": 3,
        "psnr": 25.0,
        "contact_psnr": 14.0,
    }
    assert rows[2] == {"conditioner": "label", "method": "retrieval by condition tokens", "seed": 3, "psnr": 21.0}


@pytest.mark.parametrize(
    "model, spread, expected",
    [
        (16.0, 0.1, "beats retrieval by condition tokens by 1"),
        (15.05, 0.1, "is level with retrieval"),
        (14.0, 0.1, "is behind retrieval by condition tokens by 1"),
    ],
)
def test_verdicts_count_a_gap_only_beyond_the_spread_and_ignore_the_ceiling(model, spread, expected):
    summary = [
        {"conditioner": "label", "method": "generator", "contact_psnr": model, "contact_psnr_std": spread},
        {"conditioner": "label", "method": "no-contact image", "contact_psnr": 12.0, "contact_psnr_std": 0.0},
        {
            "conditioner": "label",
            "method": "retrieval by condition tokens",
            "contact_psnr": 15.0,
            "contact_psnr_std": 0.0,
        },
        {"conditioner": "label", "method": "ceiling: tokenizer reconstruction", "contact_psnr": 30.0},
    ]
    (line,) = verdicts(summary)
    assert expected in line


def test_verdicts_on_a_lower_is_better_score():
    summary = [
        {"conditioner": "visual", "method": "generator", "contact_mae": 0.03},
        {"conditioner": "visual", "method": "no-contact image", "contact_mae": 0.05},
    ]
    (line,) = verdicts(summary, key="contact_mae")
    assert "beats no-contact image by 0.02" in line

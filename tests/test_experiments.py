"""core.experiments: the seed summary, tables and the written record every experiment shares."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from vqtouch.core import ConfigError
from vqtouch.plugins.evaluation.records import ExperimentRecord, check_seeds, format_cell, markdown_table, mean_spread


def _rows():
    # Two configurations x three seeds; the numbers are arbitrary but distinct.
    return [
        {"arm": arm, "n": n, "seed": seed, "ssim": 0.1 * seed + (0.5 if arm == "b" else 0.0), "psnr": 20.0 + seed * n}
        for arm, n in (("a", 1), ("b", 2))
        for seed in (0, 1, 2)
    ]


def test_mean_spread_matches_numpy_per_group():
    rows = _rows()
    summary = mean_spread(rows, ("ssim", "psnr"), group=("arm", "n"))
    assert [(row["arm"], row["n"]) for row in summary] == [("a", 1), ("b", 2)]  # first-seen order
    for entry in summary:
        members = [row for row in rows if row["arm"] == entry["arm"]]
        for key in ("ssim", "psnr"):
            values = np.array([row[key] for row in members])
            assert entry[key] == pytest.approx(values.mean(), abs=1e-6)
            assert entry[f"{key}_std"] == pytest.approx(values.std(ddof=0), abs=1e-6)
        assert entry["seeds"] == 3


def test_mean_spread_skips_missing_and_non_finite_values_and_says_so():
    rows = [
        {"arm": "a", "fid": 1.0},
        {"arm": "a", "fid": None},
        {"arm": "a", "fid": math.nan},
        {"arm": "a", "fid": 3.0},
        {"arm": "a"},
    ]
    (entry,) = mean_spread(rows, ("fid", "never"), group=("arm",))
    assert entry["fid"] == 2.0 and entry["fid_std"] == 1.0 and entry["fid_n"] == 2 and entry["seeds"] == 5
    assert "never" not in entry and "never_std" not in entry


def test_one_seed_has_zero_spread_and_no_plus_minus_in_the_table():
    (entry,) = mean_spread([{"arm": "a", "ssim": 0.25}], ("ssim",), group=("arm",))
    assert entry["ssim_std"] == 0.0
    lines = markdown_table([entry], ("arm",), ("ssim",))
    assert lines[-1] == "| a | 0.25 |"


def test_markdown_table_shows_mean_and_spread_and_renames_headers():
    summary = mean_spread(_rows(), ("ssim",), group=("arm", "n"))
    lines = markdown_table(summary, ("arm", "n"), ("ssim", "missing"), headers={"ssim": "SSIM"})
    assert lines[0] == "| arm | n | SSIM | missing |" and lines[1] == "|---|---|---|---|"
    assert lines[2] == f"| a | 1 | {summary[0]['ssim']:.4g} ± {summary[0]['ssim_std']:.2g} | - |"
    assert len(lines) == 2 + len(summary)


def test_format_cell():
    assert format_cell(None) == "-" and format_cell("x") == "x" and format_cell(True) == "True"
    assert format_cell(1234.5678, 0.0123) == "1235 ± 0.012" and format_cell(0.5, 0.0) == "0.5"
    # Whole numbers in full (a count of 12000 images is not "1.2e+04"), fractions to 4 significant digits.
    assert format_cell(12000.0) == "12000" and format_cell(12000) == "12000" and format_cell(12345.6) == "1.235e+04"
    assert format_cell(float("nan")) == "nan" and format_cell(3.0, 0.5) == "3 ± 0.5"


@pytest.mark.parametrize("seeds, message", [([], "at least one seed"), ([0, 1, 0], "repeats a seed")])
def test_bad_seeds_are_one_line_errors(seeds, message):
    with pytest.raises(ConfigError, match=message) as caught:
        check_seeds(seeds)
    assert "\n" not in str(caught.value)


def test_record_writes_json_with_provenance_and_markdown_with_footer(tmp_path):
    record = ExperimentRecord("toy", tmp_path / "out", seeds=[3, 4])
    summary = mean_spread(_rows(), ("ssim",), group=("arm",))
    path = record.write({"summary": summary}, ["# Toy", "", *markdown_table(summary, ("arm",), ("ssim",))])
    data = json.loads(path.read_text())
    assert path == tmp_path / "out" / "toy.json"
    assert data["experiment"] == "toy" and data["seeds"] == [3, 4] and data["summary"] == summary
    assert data["provenance"]["wall_seconds"] >= 0 and data["provenance"]["torch"]
    markdown = (tmp_path / "out" / "toy.md").read_text()
    assert markdown.startswith("# Toy\n") and "2 seeds (3, 4)" in markdown

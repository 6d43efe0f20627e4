"""bench/bench_precision.py, the script a lent GPU runs as it stands: at tiny sizes on the CPU it
measures every contender in every variant and writes what it printed."""

from __future__ import annotations

import importlib.util
import json
import math
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_the_precision_bench_measures_every_contender_and_variant(tmp_path, monkeypatch, capsys):
    monkeypatch.syspath_prepend(str(REPO / "bench"))
    spec = importlib.util.spec_from_file_location("bench_precision", REPO / "bench" / "bench_precision.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    out = tmp_path / "bench.json"
    argv = ["bench_precision.py", "--threads", "1", "--rounds", "1", "--batch", "2", "--tokenizers", "vqgan"]
    argv += ["--tokenizer-sizes", "32", "--generators", "64x2@32", "--json", str(out)]
    monkeypatch.setattr(sys, "argv", argv)
    bench.main()
    rows = {row["step"]: row for row in json.loads(out.read_text())["rows"]}
    assert set(rows) == {
        "tokenizer train, vqgan, 32 px",
        "generator train, 64x2@32",
        "generator sampling step, 64x2@32",
    }
    assert {key for key in rows["generator train, 64x2@32"] if key.endswith(" s")} == {
        f"{variant} s" for variant in bench.GENERATOR_VARIANTS
    }
    for row in rows.values():
        assert row["gflop"] > 0 and all(
            math.isfinite(value) and value > 0 for key, value in row.items() if key.endswith(" s")
        )
    printed = capsys.readouterr().out
    assert "| generator train, 64x2@32 | fp32 before | fp32 | bf16 autocast alone | bf16 |" in printed

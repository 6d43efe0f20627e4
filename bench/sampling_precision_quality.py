"""Does bf16 sampling cost quality?  A trained generator sampled in fp32 and in bf16 autocast on the same
held-out conditions and seeds, per conditioner, through ``vqtouch tradeoff generator``; then each
score's paired bf16 - fp32 difference beside the spread between sampling seeds.

Run:  .venv/bin/python bench/sampling_precision_quality.py --run pretrained:tour --out runs/sampling_precision

Each (conditioner, seed) is one ``tradeoff generator`` run at the bundle's default sampler, steps and
guidance for that conditioner (``--guidance`` per conditioner name, default 2 but 1 for ``tactile``),
``--precisions fp32 bf16``, ``--n`` held-out conditions (default 64), the classifier trained on the
tokenizer's reconstructions; a finished one is read again, so the script resumes.  Written:
``OUT/summary.json``; printed: a Markdown table.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

SCORES = ("ms_per_image", "contact_psnr", "contact_centroid_error_px", "fd_effnetlite0", "classifier_accuracy")
#: The bundles' default guidance per conditioner (their ``conditioner_guidance``; touch is unguided).
GUIDANCE = {"tactile": 1.0}


def run_one(args: argparse.Namespace, index: int, name: str, seed: int) -> dict[str, dict[str, float]]:
    """The fp32 and bf16 rows of one tradeoff run (``{precision: {score: value}}``), run if missing."""
    out = args.out / f"{index}_{name}_s{seed}"
    if not (out / "tradeoff.json").exists():
        guidance = GUIDANCE.get(name, 2.0)
        command = [sys.executable, "-m", "vqtouch.plugins.cli", "--no-progress", "--threads", str(args.threads)]
        command += ["tradeoff", "generator", "--run", args.run, "--conditioner", str(index), "--out", str(out)]
        command += ["--n", str(args.n), "--rounds", "1", "--steps", "25", "--samplers", "posterior"]
        command += ["--guidance", f"{guidance:g}", "--precisions", "fp32", "bf16", "--seed", str(seed)]
        command += ["--classifier-on", "reconstructions"]
        print("+", " ".join(command), flush=True)
        subprocess.run(command, check=True)
    rows = json.loads((out / "tradeoff.json").read_text())["settings"]
    return {
        row["precision"]: {
            key: row["seconds_per_image"] * 1000 if key == "ms_per_image" else row.get(key) for key in SCORES
        }
        for row in rows
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", default="pretrained:tour")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--conditioners", nargs="+", default=["0:label", "1:visual_cnn", "2:text_scratch", "3:tactile"])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--n", type=int, default=64)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    summary = {}
    lines = [
        "| conditioner | score | fp32 | bf16 | bf16 - fp32 (paired mean) | its spread | fp32's spread over seeds |",
        "|---|---|---|---|---|---|---|",
    ]
    for item in args.conditioners:
        index, name = item.split(":", 1)
        runs = [run_one(args, int(index), name, seed) for seed in args.seeds]
        for key in SCORES:
            fp32 = [run["fp32"][key] for run in runs if run["fp32"][key] is not None]
            bf16 = [run["bf16"][key] for run in runs if run["bf16"][key] is not None]
            if not fp32 or len(fp32) != len(bf16):
                continue
            paired = [b - f for f, b in zip(fp32, bf16)]
            spread = statistics.pstdev
            row = {
                "fp32": statistics.fmean(fp32),
                "bf16": statistics.fmean(bf16),
                "paired": statistics.fmean(paired),
                "paired_spread": spread(paired),
                "fp32_spread": spread(fp32),
            }
            summary[f"{name} {key}"] = row
            lines.append(
                f"| {name} | {key} | {row['fp32']:.3f} | {row['bf16']:.3f} | {row['paired']:+.3f} | "
                f"{row['paired_spread']:.3f} | {row['fp32_spread']:.3f} |"
            )
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()

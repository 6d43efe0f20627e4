"""Does bf16 cost quality?  Equal-step training of one component in fp32 and in bf16, a few seeds each,
through the command line; then the final scores side by side and the loss curves in one figure.

Run:  .venv/bin/python bench/precision_quality.py generator --out runs/precision_quality [--seeds 0 1 2]
      .venv/bin/python bench/precision_quality.py tokenizer --out runs/precision_quality_tok --steps 600

- ``generator``: ``vqtouch train generator --scene tour --tokenizer pretrained:tour`` for ``--steps``
  (default 1,000); scored by the held-out validation loss (lower is better; 100 held-out scenes) and
  the run's own ``generation.json`` (contact PSNR per condition, 16 samples).
- ``tokenizer``: the bundled tokenizer's recipe (``vqtouch pretrained list`` shows it) for ``--steps``;
  scored by its ``eval.json`` on the 100 held-out images: PSNR, SSIM, contact PSNR, the share of
  codes used and the best validation loss (the mean absolute error the run kept its checkpoint by).

Each (seed, precision) run is its own folder, ``OUT/<component>_<precision>_s<seed>``; a finished one is
kept and read again, so the script resumes.  ``--threads`` (default 1) goes to every run: run it beside
other work on the other core.  Written: ``OUT/summary.json``, ``OUT/loss_curves.png``; printed: a
Markdown table, with the paired bf16 - fp32 difference of each score over the seeds.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

PRECISIONS = ("fp32", "bf16")

#: The bundled ``tour`` tokenizer's recipe (its header's command), less the dataset seed.
TOKENIZER_RECIPE = [
    "--set", "tokenizer.autoencoder.channels=32", "--set", "data.batch_size=8",
    "--set", "tokenizer.loss.perceptual=none", "--set", "tokenizer.train.log_every=25",
]  # fmt: skip


def command(component: str, precision: str, seed: int, steps: int, out: Path, threads: int) -> list[str]:
    """The ``vqtouch`` command line of one run."""
    base = [
        sys.executable,
        "-m",
        "vqtouch.plugins.cli",
        "--no-progress",
        "--threads",
        str(threads),
        "train",
        component,
    ]
    settings = ["--set", f"seed={seed}", "--set", f"{component}.train.precision={precision}"]
    settings += ["--set", f"{component}.train.steps={steps}"]
    if component == "generator":
        return [*base, "--scene", "tour", "--tokenizer", "pretrained:tour", "--out", str(out), *settings]
    return [*base, "--scene", "tour", "--out", str(out), *TOKENIZER_RECIPE, *settings]


def scores(component: str, run: Path) -> dict[str, float]:
    """The final scores of a finished run (see the module docstring)."""
    if component == "generator":
        record = json.loads((run / "generation.json").read_text())
        final_val = [line for line in _metrics(run) if "val_loss" in line][-1]["val_loss"]
        row = {"val_loss": final_val}
        for name, entry in record["by_conditioner"].items():
            row[f"contact_psnr {name.split(':')[1]}"] = entry["contact_psnr"]
        return row
    record = json.loads((run / "eval.json").read_text())
    return {key: record[key] for key in ("psnr", "ssim", "contact_psnr", "codebook_usage", "best_val_loss")}


def _metrics(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines() if line.strip()]


def finished(component: str, run: Path) -> bool:
    return (run / ("generation.json" if component == "generator" else "eval.json")).is_file()


def train_all(args: argparse.Namespace) -> dict[tuple[str, int], Path]:
    """Every (precision, seed) run, interleaved by seed so a stopped script leaves pairs."""
    runs = {}
    for seed in args.seeds:
        for precision in PRECISIONS:
            run = args.out / f"{args.component}_{precision}_s{seed}"
            runs[(precision, seed)] = run
            if finished(args.component, run):
                continue
            argv = command(args.component, precision, seed, args.steps, run, args.threads)
            tic = time.perf_counter()
            subprocess.run([*argv, *(["--overwrite"] if run.exists() else [])], check=True)
            print(f"{run.name}: {time.perf_counter() - tic:.0f} s", flush=True)
    return runs


def summarise(component: str, runs: dict[tuple[str, int], Path], seeds: list[int]) -> dict:
    """Scores per run, their mean per precision and the paired bf16 - fp32 difference per seed."""
    table = {key: scores(component, run) for key, run in runs.items()}
    names = list(table[(PRECISIONS[0], seeds[0])])
    summary = {"runs": {f"{p} s{s}": row for (p, s), row in table.items()}, "scores": {}}
    for name in names:
        by = {p: [table[(p, s)][name] for s in seeds] for p in PRECISIONS}
        differences = [b - a for a, b in zip(by["fp32"], by["bf16"])]
        summary["scores"][name] = {
            **{p: statistics.mean(values) for p, values in by.items()},
            "bf16 - fp32": statistics.mean(differences),
            "spread of the difference": max(differences) - min(differences),
            "seed spread (fp32)": max(by["fp32"]) - min(by["fp32"]),
        }
    return summary


def plot_curves(component: str, runs: dict[tuple[str, int], Path], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    colours = {"fp32": "tab:blue", "bf16": "tab:orange"}
    for (precision, seed), run in sorted(runs.items()):
        lines = [line for line in _metrics(run) if line.get("stage") == component]
        train = [(line["step"], line["loss"]) for line in lines if "loss" in line]
        held_out = [(line["step"], line["val_loss"]) for line in lines if "val_loss" in line]
        label = f"{precision} seed {seed}"
        axes[0].plot(*zip(*train), color=colours[precision], alpha=0.6, lw=1, label=label)
        if held_out:
            axes[1].plot(*zip(*held_out), "o-", color=colours[precision], alpha=0.7, ms=3, label=label)
    axes[0].set(title=f"{component}: training loss", xlabel="step", yscale="log")
    axes[1].set(title="held-out loss", xlabel="step")
    axes[0].legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(path, dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("component", choices=["generator", "tokenizer"])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    runs = train_all(args)
    summary = summarise(args.component, runs, args.seeds)
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    plot_curves(args.component, runs, args.out / "loss_curves.png")
    print(f"\n{args.component}, {args.steps} steps, seeds {args.seeds}")
    print("| score | fp32 (mean) | bf16 (mean) | bf16 - fp32 (paired mean) | its spread | fp32 seed spread |")
    print("|---|---|---|---|---|---|")
    for name, row in summary["scores"].items():
        print(
            f"| {name} | {row['fp32']:.4f} | {row['bf16']:.4f} | {row['bf16 - fp32']:+.4f} | "
            f"{row['spread of the difference']:.4f} | {row['seed spread (fp32)']:.4f} |"
        )


if __name__ == "__main__":
    main()

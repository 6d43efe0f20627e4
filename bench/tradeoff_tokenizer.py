"""Speed/accuracy trade of the tokenizer, every knob in one run.

Run:  .venv/bin/python bench/tradeoff_tokenizer.py --out runs/tradeoff [--steps 150]

From one baseline (VQGAN, base channels 32, f = 4, 512 codes with the scene's cosine 8-d lookup,
fp32, 64x64 GelSight scenes, 1000 training samples, batch 8) it changes one knob at a time:
DM-VQGAN (deformable layers + fusion), codebook size 128 / 2048, the plain full-width lookup,
the EMA codebook, f = 8, bf16 autocast, DM-VQGAN in bf16 and 128x128 images.  Every
configuration trains for the same number of steps and is scored on the same 200 held-out
samples (rendered at the configuration's resolution); the table gives training seconds per
step, encode+decode images per second, SSIM, PSNR and codes used, all measured in this one run.
The baseline is trained again at the end: the gap between its two timings is the drift of the
machine during the run, the error bar of every cost ratio.
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

from experiment_tokenizers import train_and_score

KNOBS: dict[str, list[str]] = {
    "baseline (vqgan, f4, K512, fp32)": [],
    "dm_vqgan": ["tokenizer.autoencoder.name=dm_vqgan"],
    "codebook 128": ["tokenizer.quantizer.codebook_size=128"],
    "codebook 2048": ["tokenizer.quantizer.codebook_size=2048"],
    "plain lookup (full width, no cosine)": ["tokenizer.quantizer.l2_normalize=false",
                                             "tokenizer.quantizer.lookup_dim=0"],
    "ema_vq (K512)": ['tokenizer.quantizer={"name": "ema_vq", "codebook_size": 512}'],
    "f = 8": ["tokenizer.autoencoder.channel_multipliers=[1,2,2,4]"],
    "bf16": ["tokenizer.train.precision=bf16"],
    "dm_vqgan + bf16": ["tokenizer.autoencoder.name=dm_vqgan", "tokenizer.train.precision=bf16"],
    "128 px": ["data.image_size=128"],
    # The machine's speed drifts (shared cores): the baseline again, last, shows by how much.
    "baseline, repeated last": [],
}


def run_name(label: str) -> str:
    """A folder name for a knob's label."""
    return re.sub(r"[^A-Za-z0-9]+", "_", label.split(" (")[0].replace("+", "plus")).strip("_")


def with_encoder_first(base: list[str], changes: list[str]) -> list[str]:
    """The overrides of one configuration, the encoder's name first: setting a slot's name resets
    its options, so a later ``tokenizer.autoencoder.name=`` would undo ``tokenizer.autoencoder.channels=32``."""
    names = [c for c in changes if c.startswith("tokenizer.autoencoder.name=")] or ["tokenizer.autoencoder.name=vqgan"]
    return names[-1:] + base + [c for c in changes if not c.startswith("tokenizer.autoencoder.name=")]


def image_size_of(changes: list[str]) -> int:
    """The training resolution a knob sets (64 unless it sets data.image_size)."""
    sizes = [int(c.split("=", 1)[1]) for c in changes if c.startswith("data.image_size=")]
    return sizes[-1] if sizes else 64


def print_table(rows: list[dict]) -> None:
    """The trade table; cost ratios are against the repeated (last) baseline when there is one,
    because the first configuration a process trains also pays its one-time warm-up."""
    reference = next((r for r in rows if r["knob"].startswith("baseline, repeated")), rows[0])
    print(f"cost ratios against: {reference['knob']}")
    print(f"{'knob':38s} {'s/step':>7s} {'x base':>7s} {'rec img/s':>9s} {'SSIM':>7s} {'PSNR':>7s} {'codes':>6s}")
    for r in rows:
        print(f"{r['knob']:38s} {r['seconds_per_step']:7.3f} {r['seconds_per_step'] / reference['seconds_per_step']:7.2f}"
              f" {r['reconstructions_per_second']:9.1f} {r['ssim']:7.4f} {r['psnr']:7.2f} {r['codes_used']:6d}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True)
    parser.add_argument("--steps", type=int, default=150)
    parser.add_argument("--table-only", action="store_true", help="print the table of OUT/tradeoff.json and exit")
    args = parser.parse_args()
    out = Path(args.out)
    if args.table_only:
        print_table(json.loads((out / "tradeoff.json").read_text()))
        return
    base = ["tokenizer.autoencoder.channels=32", "data.dataset.num_samples=1000",
            "data.batch_size=8", f"tokenizer.train.steps={args.steps}", f"tokenizer.train.checkpoint_every={args.steps}",
            "tokenizer.train.learning_rate=0.0002", "tokenizer.loss.disc_start=100000", "seed=0"]
    rows = []
    for label, changes in KNOBS.items():
        seconds, scores = train_and_score(out / run_name(label), with_encoder_first(base, changes), "ssim,psnr",
                                          image_size_of(changes))
        rows.append({"knob": label, "seconds_per_step": seconds / args.steps,
                     "reconstructions_per_second": scores["reconstructions_per_second"], "ssim": scores["ssim"],
                     "psnr": scores["psnr"], "codes_used": scores["codes_used"]})
        print(json.dumps(rows[-1]), flush=True)
    (out / "tradeoff.json").write_text(json.dumps(rows, indent=2) + "\n")
    print()
    print_table(rows)


if __name__ == "__main__":
    main()

"""The tokenizer experiment (VQGAN vs DM-VQGAN vs MAE by training-set size): now
``vqtouch evaluate reconstruction --out``.

Run:  .venv/bin/python bench/experiment_tokenizers.py --out runs/exp_tokenizers [--steps 600]
      [any other `vqtouch evaluate reconstruction --out` flag, e.g. --samples 100 1000 --seeds 0 1 2]

This wrapper keeps the settings of the short Table 1 runs (the reconstruction scene's
tokenizer with base channels 32, 64x64 procedural GelSight scenes, batch 8, learning rate 2e-4,
the PatchGAN from step 300, 200 held-out samples) and passes every other flag to the command,
which trains each (model, N, seed) through the tokenizer stage and writes
OUT/reconstruction.json, reconstruction.md, reconstruction.png and reconstruction_samples.png.
"""

from __future__ import annotations

import argparse
import sys

from vqtouch.plugins.cli.app import main as vqtouch

#: The old script's settings as ``--set`` overrides of the reconstruction scene.
SETTINGS = [
    "tokenizer.autoencoder.channels=32",
    "data.batch_size=8",
    "tokenizer.train.learning_rate=0.0002",
    "tokenizer.loss.disc_start=300",
]


def command(out: str, steps: int, extra: list[str]) -> list[str]:
    """The ``vqtouch`` arguments of the reconstruction experiment at the old script's settings."""
    overrides = [
        item
        for override in [*SETTINGS, f"tokenizer.train.steps={steps}", f"tokenizer.train.checkpoint_every={steps}"]
        for item in ("--set", override)
    ]
    return ["--no-progress", "evaluate", "reconstruction", "--out", out, "--held-out", "200", *overrides, *extra]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True)
    parser.add_argument("--steps", type=int, default=600, help="training steps of every tokenizer (default 600)")
    args, extra = parser.parse_known_args()
    return vqtouch(command(args.out, args.steps, extra))


if __name__ == "__main__":
    sys.exit(main())

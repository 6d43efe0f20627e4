"""Speed/accuracy trade of the tokenizer, every knob in one run: now ``vqtouch evaluate tradeoff``.

Run:  .venv/bin/python bench/tradeoff_tokenizer.py --out runs/tradeoff [--steps 150]
      [any other `vqtouch evaluate tradeoff` flag, e.g. --seeds 0, --threads 1 or --knobs codebook=128]

This wrapper keeps the baseline of the tokenizer trade (VQGAN, base channels
32, f = 4, 512 codes with the scene's cosine 8-d lookup, fp32, 64x64 GelSight scenes, 1000
procedural samples, batch 8, learning rate 2e-4, no discriminator within the steps) and runs the
command's default tokenizer knobs on it: deformable layers (DM-VQGAN), codebook size 128 / 2048,
bf16 training, f = 8 and 128 px, over the command's seeds (0 1 2; the old script ran seed 0
only).  The command trains each through the tokenizer stage, scores them on the held-out split
(whole-image and contact-region scores next to the no-contact image's), times training steps and
encode + decode in interleaved rounds with the baseline first and last, and writes
OUT/tradeoff.json, tradeoff.md and tradeoff.png.  The old script's plain-lookup, ``ema_vq`` and
"DM-VQGAN + bf16" rows are not knobs of the command (measure them as another baseline, with
``--set``).
"""

from __future__ import annotations

import argparse
import sys

from vqtouch.plugins.cli.app import main as vqtouch

#: The old script's baseline as ``--set`` overrides of the reconstruction scene (the encoder's
#: name first: selecting a plugin resets its options).
BASELINE = [
    "tokenizer.autoencoder.name=vqgan",
    "tokenizer.autoencoder.channels=32",
    "data.dataset.num_samples=1000",
    "data.batch_size=8",
    "tokenizer.train.learning_rate=0.0002",
    "tokenizer.loss.adversarial_weight=0",  # the recipe these figures were measured with: no adversarial term
]


def command(out: str, steps: int, extra: list[str]) -> list[str]:
    """The ``vqtouch`` arguments of the tokenizer trade-off at the old script's baseline (the
    reconstruction scene trains no generator: the tokenizer knobs only, at their defaults)."""
    overrides = [item for override in BASELINE for item in ("--set", override)]
    return [
        "--no-progress",
        "evaluate",
        "tradeoff",
        "reconstruction",
        "--full",
        "--out",
        out,
        "--tokenizer-steps",
        str(steps),
        *overrides,
        *extra,
    ]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True)
    parser.add_argument("--steps", type=int, default=150, help="training steps of every tokenizer (default 150)")
    args, extra = parser.parse_known_args()
    return vqtouch(command(args.out, args.steps, extra))


if __name__ == "__main__":
    sys.exit(main())

"""The issue's tokenizer experiment: VQGAN vs DM-VQGAN trained on 100 and 1,000 samples.

Run:  .venv/bin/python bench/experiment_tokenizers.py --out runs/exp_tokenizers [--steps 600]
      [--samples 100 1000 10000] [--seeds 0 1 2] [--encoders vqgan dm_vqgan] [--mae-ratios 0.25 0.5 0.75]

Every run uses the reconstruction scene's objective and tokenizer (only the encoder is swapped)
at 64x64 on embedded GelSight scenes, with the same seed, batch size and number of steps; every
run is then evaluated on the SAME held-out set (200 procedural samples drawn with another seed,
never seen in training) with SSIM, PSNR, fd_effnetlite0 and codebook usage.  Prints a table and
writes results.json.  On a GPU machine the same command trains on the GPU (device "auto").
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from vqtouch.core.cli import main as vqtouch

#: Rendered by the run's own sensor (the reconstruction scene's gelsight).
HELD_OUT = {"name": "procedural", "seed": 999, "num_samples": 200, "image_size": 64}


def train_and_score(run: Path, overrides: list[str], metrics: str, image_size: int | tuple[int, int] = 64
                    ) -> tuple[float, dict]:
    """Train a tokenizer in ``run`` with ``--set`` overrides over the reconstruction scene, then
    score it on HELD_OUT rendered at ``image_size``; returns (training wall seconds, the evaluation record)."""
    tic = time.perf_counter()
    status = vqtouch(["--no-progress", "train", "tokenizer", "--scene", "reconstruction", "--out", str(run),
                      *[item for override in overrides for item in ("--set", override)]])
    seconds = time.perf_counter() - tic
    if status != 0:
        raise SystemExit(f"training {run} failed with status {status}")
    vqtouch(["evaluate", "reconstruction", "--run", str(run), "--metrics", metrics, "--dataset", json.dumps({**HELD_OUT, "image_size": image_size})])
    return seconds, json.loads(next(run.glob("evaluation_*_dataset.json")).read_text())


def json_override(path: str, value: dict) -> str:
    """A ``--set`` argument that replaces a whole slot with a JSON object."""
    return f"{path}={json.dumps(value)}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True)
    parser.add_argument("--steps", type=int, default=600)
    parser.add_argument("--channels", type=int, default=32, help="base channels of both encoders")
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--samples", type=int, nargs="+", default=[100, 1000])
    parser.add_argument("--encoders", nargs="*", default=["vqgan", "dm_vqgan"])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0],
                        help="training seeds (init, data order); each configuration is trained once per seed")
    parser.add_argument("--mae-ratios", type=float, nargs="*", default=[],
                        help="also train the MAE baseline (identity quantizer, no GAN) at these mask ratios")
    args = parser.parse_args()
    out = Path(args.out)
    results = []
    runs = [(encoder, None) for encoder in args.encoders] + [("mae", ratio) for ratio in args.mae_ratios]
    for seed, samples in ((seed, samples) for seed in args.seeds for samples in args.samples):
        for encoder, ratio in runs:
            if ratio is None:
                model = [f"tokenizer.autoencoder.name={encoder}", f"tokenizer.autoencoder.channels={args.channels}"]
                label = encoder
            else:
                model = [json_override("tokenizer.autoencoder", {"name": "mae", "mask_ratio": ratio}),
                         "tokenizer.quantizer=identity", "tokenizer.discriminator=null"]
                label = f"mae-{ratio:g}"
            run = out / (f"{label}-{samples}" if args.seeds == [0] else f"{label}-{samples}-seed{seed}")
            seconds, scores = train_and_score(run, [
                *model, f"data.dataset.num_samples={samples}", "data.val_fraction=0.1", f"data.batch_size={args.batch}",
                f"tokenizer.train.steps={args.steps}", f"tokenizer.train.checkpoint_every={args.steps}", "tokenizer.train.learning_rate=0.0002",
                "tokenizer.loss.disc_start=300", f"seed={seed}"], "ssim,psnr,fd_effnetlite0")
            results.append({"encoder": label, "train_samples": samples, "steps": args.steps, "seed": seed,
                            "train_seconds": round(seconds, 1), **{k: scores[k] for k in (
                                "ssim", "psnr", "fd_effnetlite0", "codebook_usage", "codes_used", "perplexity")}})
            print(json.dumps(results[-1]), flush=True)
    (out / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    print(f"\n{'encoder':9s} {'samples':>7s} {'seed':>4s} {'SSIM':>7s} {'PSNR':>7s} {'FD':>8s} {'usage':>6s} {'train s':>8s}")
    for r in results:
        print(f"{r['encoder']:9s} {r['train_samples']:7d} {r['seed']:4d} {r['ssim']:7.4f} {r['psnr']:7.2f} {r['fd_effnetlite0']:8.2f} "
              f"{r['codebook_usage']:6.3f} {r['train_seconds']:8.0f}")


if __name__ == "__main__":
    main()

"""DM-VQGAN at real resolutions: quality and training cost at 64, 128 and 256 px, with and without
the mid-block attention, in one run.

Run:  .venv/bin/python bench/resolution_tokenizer.py --out runs/resolution [--steps 150]
      [--sizes 64 128 256 120x160] [--encoder dm_vqgan]

Every configuration is the reconstruction scene's tokenizer (base channels 32, f = 4, 512 codes,
cosine 8-d lookup, no GAN within the steps) trained for the same number of steps on 1000
embedded GelSight scenes rendered at its resolution, batch 8, seed 0; each is scored on the same
200 held-out scenes (another seed) rendered at its resolution.  Besides SSIM and PSNR at the
training resolution, SSIM and PSNR after both images are resized to 64 px make the quality of
different resolutions comparable on the same grid.  The mid-block attention is the only attention
(``attention_resolutions`` is empty) and at f = 4 it attends over (size/4)^2 tokens: 4096 at
256 px.  ``mid_attention=false`` is the cheaper option measured beside it.  A HEIGHTxWIDTH size
(e.g. 120x160, a GelSight frame's 3:4 aspect at half of 240 x 320) renders GelSight's whole frame
(``sensor.view=full``, square pixels) instead of its centred square; its "at 64" scores resize
to 64 px wide (48 x 64).  Training seconds per
step are the whole train command's wall time over the steps; throughput and peak memory of
training and inference in isolation come from ``bench/bench_tokenizer.py --sizes 64 128 256``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch
import torch.nn.functional as F
from experiment_tokenizers import HELD_OUT, train_and_score

from vqtouch.core.image_size import ImageSize, image_hw, image_size_argument, size_text


def configurations(sizes: list[ImageSize], encoder: str) -> list[tuple[str, ImageSize, list[str]]]:
    """(label, image size, --set overrides) of every configuration: each size with and without mid attention;
    a non-square size images GelSight's whole frame (view full)."""
    return [
        (
            f"{size_text(size)} px{'' if attention else ', no mid attention'}",
            size,
            [
                f"tokenizer.autoencoder.name={encoder}",
                "tokenizer.autoencoder.channels=32",
                f"tokenizer.autoencoder.mid_attention={'true' if attention else 'false'}",
                f"data.image_size={json.dumps(list(image_hw(size)))}",
                *(["sensor.view=full"] if image_hw(size)[0] != image_hw(size)[1] else []),
            ],
        )
        for size in sizes
        for attention in (True, False)
    ]


def scores_at_64(run: Path, image_size: ImageSize) -> dict[str, float]:
    """SSIM and PSNR of the run's held-out reconstructions after resizing them and their ground truth to
    64 px wide."""
    from vqtouch.core import Assembly, load_plugins
    from vqtouch.plugins.runtime.run_dir import RunDir
    from vqtouch.plugins.tokenizer import load_tokenizer, reconstruct_all

    host = load_plugins()
    tokenizer, _ = load_tokenizer(run, host)
    assembly = Assembly(RunDir.open(run).load_config(host), host)  # the held-out scenes in the run's own sensor
    dataset = assembly.dataset({**HELD_OUT, "image_size": image_size})
    truth = torch.stack([dataset[index]["tactile"] for index in range(len(dataset))])
    with torch.no_grad():
        reconstructions = reconstruct_all(tokenizer, truth)

    height, width = image_hw(image_size)
    small_hw = (round(64 * height / width), 64)

    def to_64(images: torch.Tensor) -> torch.Tensor:
        return images if (height, width) == small_hw else F.interpolate(images, size=small_hw, mode="area")

    scores = {}
    for name in ("ssim", "psnr"):
        metric = assembly.build("metric", name)
        metric.update(to_64(reconstructions), to_64(truth))
        scores[f"{name}_at_64"] = float(metric.compute())
    return scores


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True)
    parser.add_argument("--steps", type=int, default=150)
    parser.add_argument(
        "--sizes",
        type=image_size_argument,
        nargs="+",
        default=[64, 128, 256],
        help="image sizes: S or HEIGHTxWIDTH (default 64 128 256)",
    )
    parser.add_argument("--encoder", default="dm_vqgan", choices=["vqgan", "dm_vqgan"])
    args = parser.parse_args()
    out = Path(args.out)
    base = [
        "data.dataset.num_samples=1000",
        "data.batch_size=8",
        f"tokenizer.train.steps={args.steps}",
        f"tokenizer.train.checkpoint_every={args.steps}",
        "tokenizer.train.learning_rate=0.0002",
        "tokenizer.loss.adversarial_weight=0",  # measured without the adversarial term
        "seed=0",
    ]
    rows = []
    for label, size, changes in configurations(args.sizes, args.encoder):
        run = out / label.replace(" ", "").replace(",", "_")
        seconds, scores = train_and_score(run, changes + base, "ssim,psnr", size)
        rows.append(
            {
                "configuration": label,
                "image_size": list(image_hw(size)),
                "seconds_per_step": seconds / args.steps,
                "reconstructions_per_second": scores["reconstructions_per_second"],
                "ssim": scores["ssim"],
                "psnr": scores["psnr"],
                **scores_at_64(run, size),
                "codes_used": scores["codes_used"],
            }
        )
        print(json.dumps(rows[-1]), flush=True)
    (out / "resolution.json").write_text(json.dumps(rows, indent=2) + "\n")
    print(
        f"\n{'configuration':28s} {'s/step':>7s} {'rec img/s':>9s} {'SSIM':>7s} {'PSNR':>7s} {'SSIM@64':>8s} "
        f"{'PSNR@64':>8s} {'codes':>6s}"
    )
    for r in rows:
        print(
            f"{r['configuration']:28s} {r['seconds_per_step']:7.3f} {r['reconstructions_per_second']:9.1f} "
            f"{r['ssim']:7.4f} {r['psnr']:7.2f} {r['ssim_at_64']:8.4f} {r['psnr_at_64']:8.2f} {r['codes_used']:6d}"
        )


if __name__ == "__main__":
    main()

"""What each term of the tokenizer's objective buys: L1 + VQ alone, + perceptual, + adversarial and
both, for VQGAN and DM-VQGAN (and the quantizers from the field on one recipe), at equal steps on the
bundled tokenizer's data; every run scored the same way on the same held-out images.

Run:  .venv/bin/python bench/tokenizer_terms.py --out runs/tokenizer_terms [--steps 600] [--threads 1]
          [--recipes dm_vqgan:l1_vq dm_vqgan:both ...] [--references pretrained:tour RUN ...] [--score-only]
          [--equal-wall-to dm_vqgan:both]

Each recipe is the bundled tokenizer's (``vqtouch pretrained list``: the tour scene, dataset seed 7,
32 channels, batch 8) with its loss terms and autoencoder swapped (:data:`RECIPES`), trained by
``vqtouch train tokenizer`` into ``OUT/<autoencoder>_<terms>``; a finished run is kept and scored
again, so the script resumes.  ``--equal-wall-to R`` then trains every other recipe again for as
many steps as take the time ``--steps`` of R took (seconds per step from each run's last two checkpoints), into
``OUT/<name>_at_<R>``.  Every run trains in ``--precision`` (default bf16, the fast path on a
CPU with bf16 units; the wall time of each run is printed beside it).

Scores, on the tour scene's 100 held-out images (the runs' own split):

- ``psnr``, ``ssim``, ``contact_psnr``, ``codebook_usage`` (the share of the codebook the held-out
  images use): the run's ``eval.json``;
- ``fd``: ``fd_effnetlite0`` (224 px) of the held-out images' reconstructions against the real
  held-out images, beside ``fd_real``: that of as many real *training* images against the same
  held-out images (what a perfect generator, or retrieval, would score); ``fd / fd_real`` is the
  ratio the targets are stated in;
- ``recon_only``: a linear probe on EfficientNet-Lite0 features trained only on the reconstructions of
  10 training images per class and tested on the real held-out images (mean over 3 draws), beside
  ``real_only``: the same probe on the same real training images.

Written: ``OUT/summary.json``, ``OUT/summary.md`` and ``OUT/reconstructions.png`` (the same 12
held-out images, one per class, under each recipe; the first row the real images).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

#: The bundled ``tour`` tokenizer's recipe less its loss terms and steps.
BASE = [
    "--scene",
    "tour",
    "--set",
    "data.dataset.seed=7",
    "--set",
    "data.batch_size=8",
    "--set",
    "tokenizer.train.log_every=25",
]
PATCHGAN = '{"name": "patchgan"}'
TERMS = {
    "l1_vq": ["--set", "tokenizer.loss.perceptual=none"],
    "perceptual": [],  # the scene's effnet_lite0 term at weight 0.1
    "adversarial": ["--set", "tokenizer.loss.perceptual=none", "--set", f"tokenizer.discriminator={PATCHGAN}"],
    "both": ["--set", f"tokenizer.discriminator={PATCHGAN}"],
}
QUANTIZERS = {
    "fsq": ["--set", 'tokenizer.quantizer={"name": "fsq", "levels": [8, 8, 8]}'],
    "rotation": ["--set", "tokenizer.quantizer.rotation_trick=true"],
    "simvq": ["--set", "tokenizer.quantizer.simvq=true"],
}
#: ``AUTOENCODER:TERMS[+QUANTIZER]`` -> extra command-line settings.


def autoencoder(name: str) -> list[str]:
    """The autoencoder at the bundle's 32 channels (its name first: choosing a plugin resets its options)."""
    return ["--set", f"tokenizer.autoencoder.name={name}", "--set", "tokenizer.autoencoder.channels=32"]


RECIPES = {f"{name}:{terms}": [*autoencoder(name), *TERMS[terms]] for name in ("dm_vqgan", "vqgan") for terms in TERMS}
RECIPES |= {
    f"dm_vqgan:perceptual+{name}": [*autoencoder("dm_vqgan"), *settings] for name, settings in QUANTIZERS.items()
}
PER_CLASS = 10
DRAWS = (0, 1, 2)


def folder_name(recipe: str) -> str:
    return recipe.replace(":", "_").replace("+", "_").replace("@", "_at_")


def seconds_per_step(run: Path) -> float:
    """Training seconds per step of a finished run, from its last two checkpoints' times (start-up,
    data and the final evaluation left out)."""
    *_, before, last = sorted((run / "checkpoints").glob("step-*"))
    return (last.stat().st_mtime - before.stat().st_mtime) / (int(last.name[5:]) - int(before.name[5:]))


def equal_wall_steps(recipe: str, reference: str, args: argparse.Namespace) -> int:
    """The steps of ``recipe`` that take as long as ``--steps`` of ``reference`` (both trained at equal steps)."""
    per_step = {name: seconds_per_step(args.out / folder_name(name)) for name in (recipe, reference)}
    return round(args.steps * per_step[reference] / per_step[recipe])


def train(recipe: str, out: Path, args: argparse.Namespace, steps: int) -> float | None:
    """Train one recipe for ``steps`` unless finished; its wall time in seconds (None when it was already there)."""
    if (out / "eval.json").is_file():
        return None
    argv = [sys.executable, "-m", "vqtouch.plugins.cli", "--no-progress", "--threads", str(args.threads)]
    argv += ["train", "tokenizer", *BASE, *RECIPES[recipe.split("@")[0]], "--out", str(out)]
    argv += ["--set", f"tokenizer.train.steps={steps}", "--set", f"tokenizer.train.precision={args.precision}"]
    if out.exists():
        argv += ["--overwrite"]
    print("$", " ".join(argv[1:]), flush=True)
    tic = time.perf_counter()
    subprocess.run(argv, check=True)
    seconds = time.perf_counter() - tic
    (out / "wall_seconds.txt").write_text(f"{seconds:.1f}\n")
    return seconds


class Scorer:
    """The held-out images, the training draws and the feature network, made once for every run."""

    def __init__(self, run: Path, host) -> None:
        from vqtouch.core import Assembly
        from vqtouch.plugins.runtime.run_dir import RunDir
        from vqtouch.plugins.utils.splits import experiment_split
        from vqtouch.plugins.experiments.downstream_arms import draw_others
        from vqtouch.plugins.experiments.downstream_inputs import real_features

        self.config = RunDir.open(run).load_config(host)
        assembly = Assembly(self.config, host)
        self.dataset = assembly.component("data.dataset")
        train_split, test_split = experiment_split(self.dataset, self.config.data, self.config.seed)
        self.metric = assembly.build("metric", {"name": "fd_effnetlite0", "image_size": 224})
        self.train_indices = list(train_split.indices)
        self.test_indices = list(test_split.indices)
        self.test, _ = real_features(self.dataset, self.test_indices, self.metric)
        train_labels = [int(self.dataset[i]["label"]) for i in self.train_indices]
        self.draws = {
            seed: [self.train_indices[p] for p in draw_others(train_labels, PER_CLASS, seed, [])] for seed in DRAWS
        }
        real_pool = torch.randperm(len(self.train_indices), generator=torch.Generator().manual_seed(0))
        self.real_reference, _ = real_features(
            self.dataset, [self.train_indices[p] for p in real_pool[: len(self.test_indices)].tolist()], self.metric
        )
        first_of_class: dict[int, int] = {}
        for index, label in zip(self.test_indices, self.test.labels):
            first_of_class.setdefault(label, index)
        self.shown = [first_of_class[label] for label in sorted(first_of_class)]

    def probe(self, prepare) -> float:
        """Mean top-1 on the real held-out images of the probe trained on ``prepare`` of each draw."""
        from vqtouch.plugins.experiments.downstream import train_and_test
        from vqtouch.plugins.experiments.downstream_inputs import real_features

        top1 = []
        for seed, indices in self.draws.items():
            train, _ = real_features(self.dataset, indices, self.metric, prepare)
            top1.append(train_and_test(train, self.test, seed)[0]["top1"])
        return statistics.mean(top1)

    def score(self, tokenizer) -> tuple[dict[str, float], torch.Tensor]:
        from vqtouch.plugins.evaluation.fd_metric import feature_frechet_distance
        from vqtouch.plugins.experiments.downstream_inputs import real_features
        from vqtouch.plugins.tokenizer import reconstruct_all

        def reconstruct(images_N3HW):
            with torch.no_grad():
                return reconstruct_all(tokenizer, images_N3HW, 32).float().clamp(0, 1)

        recon_test, _ = real_features(self.dataset, self.test_indices, self.metric, reconstruct)
        shown = torch.stack([self.dataset[i]["tactile"] for i in self.shown]).float()
        return {
            "fd": feature_frechet_distance(recon_test.features_NF, self.test.features_NF),
            "recon_only": self.probe(reconstruct),
        }, reconstruct(shown)

    def reference(self) -> dict[str, float]:
        from vqtouch.plugins.evaluation.fd_metric import feature_frechet_distance

        return {
            "fd_real": feature_frechet_distance(self.real_reference.features_NF, self.test.features_NF),
            "real_only": self.probe(None),
        }


def eval_scores(run: Path) -> dict[str, float]:
    record = json.loads((run / "eval.json").read_text())
    return {key: record.get(key) for key in ("psnr", "ssim", "contact_psnr", "codebook_usage")}


def reference_eval(name: str, scorer: Scorer, host) -> dict[str, float]:
    """PSNR, SSIM, contact PSNR and code usage of a tokenizer that is not a run (a bundle)."""
    from vqtouch.core import Assembly
    from vqtouch.plugins.utils.splits import experiment_split
    from vqtouch.plugins.evaluation.contact import dataset_background
    from vqtouch.plugins.tokenizer import load_tokenizer
    from vqtouch.plugins.tokenizer.training import evaluate_reconstruction

    tokenizer, _ = load_tokenizer(name, host)
    assembly = Assembly(scorer.config, host)
    train_split, test_split = experiment_split(scorer.dataset, scorer.config.data, scorer.config.seed)
    background, _ = dataset_background(train_split, tuple(test_split[0]["tactile"].shape[-2:]))
    metrics = {name: assembly.build("metric", {"name": name}) for name in ("psnr", "ssim")}
    scores = evaluate_reconstruction(tokenizer, test_split, metrics, background_3HW=background)
    return {key: scores.get(key) for key in ("psnr", "ssim", "contact_psnr", "codebook_usage")}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--steps", type=int, default=600)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--precision", default="bf16", choices=("fp32", "bf16", "auto"))
    parser.add_argument("--recipes", nargs="+", default=list(RECIPES), choices=list(RECIPES))
    parser.add_argument(
        "--references",
        nargs="*",
        default=["pretrained:tour"],
        help="tokenizers scored beside the recipes: bundles (pretrained:NAME) or finished tokenizer runs",
    )
    parser.add_argument(
        "--equal-wall-to",
        choices=list(RECIPES),
        help="also train every other recipe for as long as --steps of this one took (after the equal-step runs)",
    )
    parser.add_argument("--score-only", action="store_true", help="score the finished runs; train nothing")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    recipes = list(args.recipes)
    if args.equal_wall_to:
        recipes += [f"{recipe}@{args.equal_wall_to}" for recipe in args.recipes if recipe != args.equal_wall_to]
    if not args.score_only:
        for recipe in recipes:
            base, _, reference = recipe.partition("@")
            steps = equal_wall_steps(base, reference, args) if reference else args.steps
            seconds = train(recipe, args.out / folder_name(recipe), args, steps)
            if seconds is not None:
                print(f"{recipe}: {steps} steps trained in {seconds:.0f} s", flush=True)
    finished = [r for r in recipes if (args.out / folder_name(r) / "eval.json").is_file()]
    if not finished:
        print("no finished run to score")
        return 1
    return summarise(args, finished)


def summarise(args: argparse.Namespace, finished: list[str]) -> int:
    from vqtouch.core import load_plugins
    from vqtouch.plugins.utils.images import image_grid, save_png
    from vqtouch.plugins.tokenizer import load_tokenizer

    host = load_plugins()
    scorer = Scorer(args.out / folder_name(finished[0]), host)
    reference = scorer.reference()
    rows, pictures = [], [torch.stack([scorer.dataset[i]["tactile"] for i in scorer.shown]).float()]
    for name in [*args.references, *finished]:
        tic = time.perf_counter()
        if name.startswith("pretrained:"):
            tokenizer, _ = load_tokenizer(name, host)
            row = {"recipe": name, **reference_eval(name, scorer, host), "wall_s": None}
        else:
            run = Path(name) if name in args.references else args.out / folder_name(name)
            tokenizer, _ = load_tokenizer(run, host)
            wall = run / "wall_seconds.txt"
            row = {
                "recipe": name,
                **eval_scores(run),
                "steps": json.loads((run / "eval.json").read_text())["step"],
                "s_per_step": seconds_per_step(run),
                "wall_s": float(wall.read_text()) if wall.is_file() else None,
            }
        extra, shown = scorer.score(tokenizer)
        row |= extra | {"fd_ratio": extra["fd"] / reference["fd_real"]}
        rows.append(row)
        pictures.append(shown)
        print(f"{name}: scored in {time.perf_counter() - tic:.0f} s: {row}", flush=True)
    summary = {"steps": args.steps, "precision": args.precision, "reference": reference, "rows": rows}
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    save_png(image_grid(torch.cat(pictures), columns=len(scorer.shown)), args.out / "reconstructions.png")
    lines = [
        f"real training images: fd {reference['fd_real']:.1f}, probe {reference['real_only']:.3f}",
        "",
        "| recipe | steps | s/step | PSNR dB | SSIM | contact PSNR dB | code usage | fd (x real) | recon-only probe | "
        "run s |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        wall = "-" if row["wall_s"] is None else f"{row['wall_s']:.0f}"
        steps = f"{row['steps']} | {row['s_per_step']:.2f}" if "steps" in row else "- | -"
        usage = "-" if row["codebook_usage"] is None else f"{row['codebook_usage']:.2f}"
        lines.append(
            f"| {row['recipe']} | {steps} | {row['psnr']:.2f} | {row['ssim']:.4f} | {row['contact_psnr']:.2f} "
            f"| {usage} "
            f"| {row['fd']:.1f} ({row['fd_ratio']:.2f}x) | {row['recon_only']:.3f} | {wall} |"
        )
    (args.out / "summary.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

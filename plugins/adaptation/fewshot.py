"""``vqtouch evaluate fewshot --run FAMILY_RUN --out DIR``: the paper's Table 4, few-shot reconstruction
of an unseen sensor from N of its images.

::

    vqtouch evaluate fewshot --run runs/tok --out runs/exp/fewshot [--target SPEC] [--n 500 2000] [--ratio 5] \\
        [--steps 200] [--scratch-steps S] [--eval-images 64] [--families DIR] [--seeds 0 1 2] [--overwrite]

The unseen sensor (``--target``: by default the zero-shot scene's damaged, drifted GelSight; any
registered sensor, a variant as JSON, or a folder of a real sensor's images) gives N images per
seed (the shots: rendered scenes, or a seeded draw from the folder), and four arms learn from them:

1. ``scratch``: a fresh tokenizer with the family run's config, trained on the N images alone for
   ``--scratch-steps`` (default: the run's own ``tokenizer.train.steps``);
2. ``zero-shot``: the family tokenizer unchanged (scored once per seed; it does not depend on N,
   and the table repeats it under every N);
3. ``shots alone``: the family tokenizer fine-tuned ``--steps`` on the N images (``vqtouch adapt``
   with ratio 0);
4. ``mixed 1:5``: the family tokenizer fine-tuned ``--steps`` on the N images plus ``--ratio`` times
   as many images of its family's members (VQ-Touch's mix, ``vqtouch adapt``).

Every arm of a seed is scored on the same held-out images of the sensor (``--eval-images``; for a
folder, the same last images of the seed's shuffle, so the largest N must leave at least one):
SSIM, PSNR, ``fd_effnetlite0`` (listed as skipped with the reason where it cannot run), codebook
usage, and next to them the same scores of the sensor's **no-contact background** (a registered
sensor rendering no contact; for a folder, the per-pixel median of its images) and the
**contact-region** scores (contact PSNR/SSIM/MAE on the pixels where the held-out image differs
from that background).  The sensor is assigned to a family once per seed from the smallest N's
shots; every fine-tuned arm of the seed adapts from that family (its nearest one, said so, when
the assignment is refused).  Families come from ``--families`` (a ``vqtouch cluster`` output of
this tokenizer) or are clustered once from every registered sensor family and 3 variants of each
(written to ``DIR/families``), as ``vqtouch adapt`` does.

Writes ``fewshot.json`` (every arm x N x seed row, mean ± std over the seeds, the assignments,
provenance), ``fewshot.md`` (one table grouped by N and arm with a ``no-contact background`` row
per N, and verdicts that compare the mixed arm with every other on the contact PSNR only, when the
gap exceeds both spreads), ``fewshot.png`` (contact PSNR and SSIM against N per arm, the
background as a line) and every trained arm's tokenizer in ``DIR/seed<S>/<arm>-<N>/`` (``scratch``,
``shots``, ``mixed``; ``vqtouch adapt``'s ``adapt.json`` beside the fine-tuned ones).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Callable, Sequence

import torch

from vqtouch.core import ConfigError, PluginHost
from vqtouch.plugins.evaluation.records import (
    ExperimentRecord,
    check_seeds,
    gap_verdict,
    markdown_table,
    mean_spread,
    plot_against_count,
    refuse_finished,
)
from vqtouch.core.image_size import ImageSize, size_text
from vqtouch.plugins.evaluation.directions import direction_arrow

from .adapt import AdaptSettings, adapt_tokenizer, reconstruction_scores
from .adapt_images import sensor_background, target_images
from .evaluation import METRICS
from .experiment_inputs import families_for, held_out_count, report_seed_family
from .families import SensorFamilies
from .scratch import train_fresh_tokenizer

SCRATCH, ZERO_SHOT, SHOTS_ALONE, BACKGROUND = "scratch", "zero-shot", "shots alone", "no-contact background"
#: The held-out scores every arm carries, and its background's under the ``background_`` prefix.
SCORES = ("ssim", "psnr", "contact_ssim", "contact_psnr", "contact_mae", "fd_effnetlite0")
#: What the table shows per (N, arm), in order.
TABLE_COLUMNS = (
    "train_images",
    "ssim",
    "psnr",
    "contact_ssim",
    "contact_psnr",
    "fd_effnetlite0",
    "codebook_usage",
    "family_psnr",
    "seconds",
)
#: Numbers of a row averaged over the seeds (the table's and the JSON's).
SUMMARY_KEYS = (
    *TABLE_COLUMNS,
    "contact_mae",
    "family_images",
    "family_ssim",
    "family_psnr",
    *(f"background_{key}" for key in SCORES),
    "contact_fraction",
)
#: The verdicts compare on this contact-region score only (whole-image scores flatter the background).
VERDICT_KEY = "contact_psnr"


def mixed_arm(ratio: float) -> str:
    """The mixed arm's name: ``mixed 1:5`` for ratio 5."""
    return f"mixed 1:{ratio:g}"


def check_counts(counts: Sequence[int]) -> list[int]:
    """``counts`` (the N) ascending, refusing an empty list, a repeat or a count below 1."""
    counts = list(counts)
    if not counts or min(counts) < 1:
        raise ConfigError(f"--n {' '.join(map(str, counts))}: give one or more image counts of at least 1")
    if len(set(counts)) != len(counts):
        raise ConfigError(f"--n {' '.join(map(str, counts))} repeats a count; give distinct counts")
    return sorted(counts)


def _scores(scores: dict[str, Any]) -> dict[str, Any]:
    """One arm's held-out scores as a row's columns (the background's keep their prefix)."""
    keys = (*SCORES, "codebook_usage", "contact_fraction", *(f"background_{key}" for key in SCORES))
    return {key: scores[key] for key in keys if key in scores}


def _adapted_row(n: int, arm: str, seed: int, summary: dict[str, Any]) -> dict[str, Any]:
    """A fine-tuned arm's row from its ``adapt.json`` summary."""
    family = summary["family_held_out"]["after"]
    return {
        "n": n,
        "arm": arm,
        "seed": seed,
        "train_images": summary["shots"] + summary["family_images"],
        "family_images": summary["family_images"],
        "steps": summary["steps"],
        "held_out": summary["held_out"],
        **_scores(summary["after"]),
        "family_ssim": family["ssim"],
        "family_psnr": family["psnr"],
        "seconds": summary["seconds"],
    }


def _background_row(n: int, seed: int, scores: dict[str, Any]) -> dict[str, Any]:
    """The no-contact background's row: its ``background_*`` scores without the prefix, beside the arms'."""
    return {
        "n": n,
        "arm": BACKGROUND,
        "seed": seed,
        "train_images": 0,
        "held_out": scores["samples"],
        **{key: scores[f"background_{key}"] for key in SCORES if f"background_{key}" in scores},
        "contact_fraction": scores.get("contact_fraction"),
    }


def seed_arms(
    run: Any,
    target: str,
    families: SensorFamilies,
    family: int,
    host: PluginHost,
    out: Path,
    *,
    seed: int,
    counts: Sequence[int],
    ratio: float,
    steps: int,
    scratch_steps: int,
    held_out: int,
    batch_size: int,
    background_3HW: torch.Tensor,
    image_size: ImageSize,
    report: Callable[[str], None] = print,
) -> tuple[list[dict[str, Any]], dict[str, str]]:
    """One seed's rows: at every N the four arms and the background, in the table's order, and the
    metrics skipped with their reasons.  Every arm scores the same ``held_out`` images in batches of
    ``batch_size`` (the fine-tuning batch too)."""
    rows: list[dict[str, Any]] = []
    skipped: dict[str, str] = {}
    zero_shot = None
    for n in counts:
        summaries = _fine_tuned_arms(
            run, target, families, family, host, out, seed, n, ratio, steps, held_out, batch_size, background_3HW
        )
        # The family tokenizer before any fine-tuning, on the same held-out images: the zero-shot arm (and
        # its score on the family's held-out images, what the fine-tuned arms keep or forget of the family).
        zero_shot = zero_shot or summaries[SHOTS_ALONE]["before"]
        family_before = summaries[SHOTS_ALONE]["family_held_out"]["before"]
        scratch_row, scratch = _scratch_arm(
            run, target, host, out, seed, n, scratch_steps, held_out, batch_size, background_3HW, image_size
        )
        rows.append(scratch_row)
        rows.append(_zero_shot_row(n, seed, zero_shot, family_before))
        rows += [_adapted_row(n, arm, seed, summary) for arm, summary in summaries.items()]
        rows.append(_background_row(n, seed, zero_shot))
        for scores in (scratch, zero_shot, *(summary["after"] for summary in summaries.values())):
            skipped |= scores.get("skipped") or {}
        report(
            f"seed {seed}, N {n}: contact PSNR "
            + ", ".join(f"{row['arm']} {row.get(VERDICT_KEY, '-')}" for row in rows if row["n"] == n)
        )
    return rows, skipped


def _fine_tuned_arms(
    run: Any,
    target: str,
    families: SensorFamilies,
    family: int,
    host: PluginHost,
    out: Path,
    seed: int,
    n: int,
    ratio: float,
    steps: int,
    held_out: int,
    batch_size: int,
    background_3HW: torch.Tensor,
) -> dict[str, dict[str, Any]]:
    """The shots-alone and mixed arms at one N: each arm's ``adapt.json`` summary, by arm."""
    summaries = {}
    for arm, arm_ratio, name in ((SHOTS_ALONE, 0.0, "shots"), (mixed_arm(ratio), ratio, "mixed")):
        settings = AdaptSettings(
            shots=n,
            ratio=arm_ratio,
            steps=steps,
            eval_images=held_out,
            seed=seed,
            family=family,
            batch_size=batch_size,
            metrics=METRICS,
        )
        summaries[arm] = adapt_tokenizer(
            run,
            target,
            families,
            host,
            out / f"seed{seed}" / f"{name}-{n}",
            settings,
            overwrite=True,
            report=lambda line: None,
            background_3HW=background_3HW,
        )
    return summaries


def _scratch_arm(
    run: Any,
    target: str,
    host: PluginHost,
    out: Path,
    seed: int,
    n: int,
    scratch_steps: int,
    held_out: int,
    batch_size: int,
    background_3HW: torch.Tensor,
    image_size: ImageSize,
) -> tuple[dict[str, Any], dict[str, Any]]:
    """The scratch arm at one N: a fresh tokenizer trained on the N shots alone; its row and scores."""
    _, source, shots_N, held_out_M = target_images(
        target, host, shots=n, eval_images=held_out, image_size=image_size, seed=seed
    )
    metadata = {"fewshot.arm": SCRATCH, "fewshot.target": source, "fewshot.train_images": str(n)}
    tokenizer, trained = train_fresh_tokenizer(
        run,
        shots_N,
        host,
        seed=seed,
        steps=scratch_steps,
        out=out / f"seed{seed}" / f"{SCRATCH}-{n}",
        metadata=metadata,
    )
    scratch = reconstruction_scores(tokenizer, held_out_M, host, batch_size, METRICS, background_3HW)
    row = {
        "n": n,
        "arm": SCRATCH,
        "seed": seed,
        "train_images": trained["train_images"],
        "family_images": 0,
        "steps": trained["steps"],
        "held_out": len(held_out_M),
        **_scores(scratch),
        "seconds": trained["seconds"],
    }
    return row, scratch


def _zero_shot_row(n: int, seed: int, zero_shot: dict[str, Any], family_before: dict[str, Any]) -> dict[str, Any]:
    """The family tokenizer's row, unchanged: the same scores under every N."""
    return {
        "n": n,
        "arm": ZERO_SHOT,
        "seed": seed,
        "train_images": 0,
        "family_images": 0,
        "steps": 0,
        "held_out": zero_shot["samples"],
        **_scores(zero_shot),
        "family_ssim": family_before["ssim"],
        "family_psnr": family_before["psnr"],
        "seconds": 0.0,
    }


def evaluate_fewshot(
    run: str | Path,
    host: PluginHost,
    out: str | Path,
    *,
    target: str,
    seeds: Sequence[int],
    counts: Sequence[int] = (500, 2000),
    ratio: float = 5.0,
    steps: int = 200,
    scratch_steps: int | None = None,
    eval_images: int = 64,
    families: str | Path | None = None,
    overwrite: bool = False,
    report: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Run the experiment of the module docstring and write its files into ``out``.

    ``run``: the family tokenizer's run (its config builds the scratch arm); ``target``: the unseen
    sensor (registered name, JSON variant or folder); ``counts``: the N; ``ratio``: family images per
    target image of the mixed arm; ``steps``: fine-tuning steps; ``scratch_steps``: the scratch arm's
    (default the run's ``tokenizer.train.steps``); ``eval_images``: held-out images (fewer when a
    folder cannot spare them); ``families``: a ``vqtouch cluster`` folder (default: clustered here).
    Every bad input is refused with a one-line ConfigError before anything trains.  Returns what
    ``fewshot.json`` holds."""
    from vqtouch.plugins.runtime.run_dir import RunDir
    from vqtouch.plugins.tokenizer import load_tokenizer

    out = Path(out)
    refuse_finished(out, "fewshot", "a fewshot experiment", overwrite)
    seeds = check_seeds(seeds)
    counts = check_counts(counts)
    _check_ratio_and_run(ratio, run)
    config = RunDir.open(run).load_config(host)
    scratch_steps = scratch_steps or config.tokenizer.train.steps
    tokenizer, folder = load_tokenizer(run, host)
    image_size = tokenizer.autoencoder.vqtouch_spec.context.image_size
    held_out = held_out_count(target, counts, eval_images, host)  # before anything trains or renders
    # One scoring batch for every arm: the contact region's noise estimate is made per batch, so the
    # arms' regions (and the background's scores) are the same pixels only when the batches are.  It
    # is the run's batch, or the smallest N when that is smaller (the fine-tuning batch then too).
    batch_size = min(config.data.batch_size, counts[0])
    background, background_source = sensor_background(target, host, image_size)
    record = ExperimentRecord("fewshot", out, seeds, overwrite=overwrite)
    fitted, families_source = families_for(families, tokenizer, folder, target, host, out, image_size)
    # What fewshot.json records of the settings, and what every seed's arms run with (:func:`seed_arms`).
    settings = {
        "counts": counts,
        "ratio": ratio,
        "steps": steps,
        "scratch_steps": scratch_steps,
        "batch_size": batch_size,
        "held_out": held_out,
    }
    rows, skipped, assignments, name, source = _run_seeds(
        run, target, fitted, tokenizer, host, out, record.seeds, background, image_size, settings, report
    )
    summary = mean_spread(rows, SUMMARY_KEYS, ("n", "arm"))
    result = {
        "run": str(run),
        "tokenizer": str(folder),
        "target": name,
        "target_source": source,
        "background": background_source,
        "image_size": image_size,
        **settings,
        "families": families_source,
        "assignments": assignments,
        "rows": rows,
        "summary": summary,
        "skipped": skipped,
    }
    _plot_fewshot(summary, record.path("fewshot.png"), name, len(record.seeds), steps)
    record.write(result, render_markdown(result))
    return result


def _run_seeds(
    run: str | Path,
    target: str,
    fitted: SensorFamilies,
    tokenizer: Any,
    host: PluginHost,
    out: Path,
    seeds: Sequence[int],
    background_3HW: torch.Tensor,
    image_size: ImageSize,
    settings: dict[str, Any],
    report: Callable[[str], None],
) -> tuple[list[dict[str, Any]], dict[str, str], list[dict[str, Any]], str, str]:
    """Every seed's family and arms (:func:`seed_arms` with ``settings``): the rows, the metrics skipped,
    the assignments, and the sensor's name and source."""
    rows: list[dict[str, Any]] = []
    skipped: dict[str, str] = {}
    assignments = []
    name = source = ""
    for seed in seeds:
        # One family per seed, from the smallest N's shots (what every arm has): only N changes between the
        # fine-tuned arms of a seed.
        name, source, assignment = report_seed_family(
            fitted,
            tokenizer,
            target,
            host,
            shots=settings["counts"][0],
            eval_images=settings["held_out"],
            image_size=image_size,
            seed=seed,
            report=report,
        )
        assignments.append(assignment)
        seed_rows, seed_skipped = seed_arms(
            run,
            target,
            fitted,
            assignment["family"],
            host,
            out,
            seed=seed,
            background_3HW=background_3HW,
            image_size=image_size,
            report=report,
            **settings,
        )
        rows += seed_rows
        skipped |= seed_skipped
    return rows, skipped, assignments, name, source


def _check_ratio_and_run(ratio: float, run: str | Path) -> None:
    """Refuse a mixed arm without family images, and a ``run`` that is no run directory."""
    if not (ratio > 0 and math.isfinite(ratio)):
        raise ConfigError(
            f"--ratio {ratio:g}: the mixed arm needs family images (a finite ratio > 0; the shots-alone arm is ratio 0)"
        )
    if not (run and (Path(run) / "config.json").is_file()):
        raise ConfigError(
            f"--run {run}: not a run directory (no config.json); the scratch arm trains a fresh "
            "tokenizer with the run's config, so give the family tokenizer's run"
        )


def _plot_fewshot(summary: list[dict[str, Any]], path: Path, name: str, seed_count: int, steps: int) -> None:
    """``fewshot.png``: contact PSNR and SSIM against N per arm, the background as a line."""
    plot_against_count(
        summary,
        count="n",
        line="arm",
        keys=("contact_psnr", "contact_ssim"),
        path=path,
        xlabel="N: unseen-sensor images",
        dashed=(BACKGROUND,),
        title=f"few-shot reconstruction of {name} ({seed_count} seeds, {steps} fine-tuning steps)",
    )


def verdict_lines(
    summary: Sequence[dict[str, Any]], counts: Sequence[int], ratio: float, key: str = VERDICT_KEY
) -> list[str]:
    """Per N, the mixed arm against every other arm and the background on the contact-region score
    ``key`` (:func:`vqtouch.plugins.evaluation.records.gap_verdict`: a gap counts beyond both spreads)."""
    lines = []
    mixed = mixed_arm(ratio)
    for n in counts:
        rows = {row["arm"]: row for row in summary if row["n"] == n and key in row}
        if mixed not in rows:
            continue
        for arm in (SCRATCH, ZERO_SHOT, SHOTS_ALONE, BACKGROUND):
            if arm in rows:
                lines.append(f"- N = {n}: {mixed} {gap_verdict(rows[mixed], rows[arm], key, arm)} on {key}.")
    return lines


def render_markdown(result: dict[str, Any]) -> list[str]:
    """The table and verdicts of ``fewshot.json`` for people."""
    mixed = mixed_arm(result["ratio"])
    fractions = [
        row["contact_fraction"]
        for row in result["rows"]
        if row["arm"] == BACKGROUND and row.get("contact_fraction") is not None
    ]
    region = (
        f"the contact region is {100 * sum(fractions) / len(fractions):.3g}% of their pixels"
        if fractions
        else "no contact region was found"
    )
    refused = [entry["seed"] for entry in result["assignments"] if entry["refused"]]
    lines = [
        f"# Few-shot reconstruction of an unseen sensor (Table 4; {len(result['assignments'])} seeds: mean ± std)",
        "",
        f"Family tokenizer `{result['tokenizer']}`, {size_text(result['image_size'])} px; unseen sensor "
        f"`{result['target']}`.  At every N: `{SCRATCH}` trains a fresh tokenizer with the run's config on the N "
        f"images alone ({result['scratch_steps']} steps); `{ZERO_SHOT}` is the family tokenizer unchanged (the "
        f"same at every N); `{SHOTS_ALONE}` fine-tunes it {result['steps']} steps on the N images; `{mixed}` "
        f"fine-tunes it {result['steps']} steps on the N images plus {result['ratio']:g} x N images of its "
        f"family.  Every arm of a seed scores the same {result['held_out']} held-out images of the sensor; "
        f"{region}.  `{BACKGROUND}`: {result['background']}, scored against the same images.  `contact_*`: "
        "scores on the contact region only; `family_psnr`: PSNR on held-out images of the family's members (what "
        "an arm keeps of the family, the mix's purpose); `seconds`: training wall time.  Arrows: "
        + ", ".join(f"{key} {direction_arrow(key)}" for key in TABLE_COLUMNS[1:-1])
        + ".",
        "",
        *markdown_table(result["summary"], ("n", "arm"), TABLE_COLUMNS, {"n": "N", "train_images": "train images"}),
        "",
        f"Verdicts ({mixed} against each other arm, on the contact region only; a gap counts when it exceeds "
        "both spreads):",
        "",
        *(
            verdict_lines(result["summary"], result["counts"], result["ratio"])
            or ["- no contact-region score to compare"]
        ),
        "",
        "Families: "
        + result["families"]
        + "; "
        + "; ".join(
            f"seed {entry['seed']}: family {entry['family']} ({', '.join(entry['members'])})"
            for entry in result["assignments"]
        )
        + ".",
    ]
    if refused:
        lines += [
            "",
            f"The assignment was refused (beyond the threshold) for seed(s) {refused}: those seeds adapt "
            "from the nearest family.",
        ]
    if result["skipped"]:
        lines += [
            "",
            "Skipped: " + "; ".join(f"`{name}`: {reason}" for name, reason in sorted(result["skipped"].items())),
        ]
    return lines

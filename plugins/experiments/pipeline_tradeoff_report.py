"""The columns of ``vqtouch evaluate tradeoff``'s rows and what is made of them
(:mod:`vqtouch.plugins.experiments.pipeline_tradeoff`): the mean ± std summary with its Pareto fronts,
``tradeoff.md``'s table and ``tradeoff.png``'s plots."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from vqtouch.plugins.evaluation.records import markdown_table, mean_spread

#: The ``setting`` of the baseline's second timing in every round (its ``x base`` is the drift).
DRIFT = "timed again last"
#: Whole-image and contact-region quality columns; each stands next to its ``background_`` score.
QUALITY_KEYS = ("ssim", "psnr", "contact_ssim", "contact_psnr")
COST_KEYS = ("train_s_per_step", "train_cost", "img_per_s", "seconds_per_image", "inference_cost", "stage_seconds")
SUMMARY_KEYS = (
    *COST_KEYS,
    *QUALITY_KEYS,
    *(f"background_{key}" for key in QUALITY_KEYS),
    "codes_used",
    "contact_fraction",
    "fd_effnetlite0",
    "classifier_accuracy",
)
#: The Pareto fronts: (part, cost column, name in the table).
FRONTS = (
    ("tokenizer", "train_cost", "training"),
    ("tokenizer", "inference_cost", "inference"),
    ("generator", "inference_cost", "generation"),
)


#: The scores the fronts are drawn on, the first one the rows have: contact SSIM; contact PSNR for
#: images narrower than SSIM's window; whole-image SSIM only without a background (no contact region).
FRONT_QUALITIES = ("contact_ssim", "contact_psnr", "ssim")
FRONT_TEXT = {
    "contact_ssim": "the contact region's SSIM: claims of 'better' rest on it, not on the whole-image scores",
    "contact_psnr": "the contact region's PSNR (the images are narrower than SSIM's window): claims of "
    "'better' rest on it, not on the whole-image scores",
    "ssim": "whole-image SSIM, because the training split is too small for a no-contact image: without one "
    "there is no contact region, and whole-image scores flatter a model that draws only the "
    "background",
}
AXIS_LABELS = {"contact_ssim": "contact SSIM", "contact_psnr": "contact PSNR (dB)", "ssim": "whole-image SSIM"}


def front_quality_key(rows: list[dict[str, Any]]) -> str:
    """The score the Pareto fronts use (:data:`FRONT_QUALITIES`)."""
    return next((key for key in FRONT_QUALITIES if any(key in row for row in rows)), FRONT_QUALITIES[0])


def summarize(rows: list[dict[str, Any]]) -> tuple[list[dict[str, Any]], str]:
    """Mean ± std over the seeds of every (part, knob, setting), each with ``pareto``: the fronts
    (training, inference, generation) it is on, on the mean relative cost against the mean contact
    score (the drift rows are no contenders).  Also returns that score's key."""
    summary = mean_spread(rows, SUMMARY_KEYS, group=("part", "knob", "setting"))
    key = front_quality_key(rows)
    for row in summary:
        row["pareto"] = []
    for part, cost, name in FRONTS:
        members = [row for row in summary if row["part"] == part and row["setting"] != DRIFT]
        costs = [row.get(cost, math.nan) for row in members]
        for index in pareto_front(costs, [row.get(key) for row in members]):
            members[index]["pareto"].append(name)
    for row in summary:
        row["pareto_front"] = ", ".join(row["pareto"]) or "-"
    return summary, key


def pareto_front(costs: list[float], qualities: list[float | None]) -> list[int]:
    """:func:`vqtouch.plugins.generator.tradeoff.pareto_front`, higher quality better."""
    from vqtouch.plugins.generator import pareto_front as front

    return front(costs, qualities, higher_is_better=True)


TABLE_KEYS = (
    "train_s_per_step",
    "train_cost",
    "img_per_s",
    "inference_cost",
    "ssim",
    "background_ssim",
    "psnr",
    "background_psnr",
    "contact_ssim",
    "background_contact_ssim",
    "contact_psnr",
    "background_contact_psnr",
    "codes_used",
    "pareto_front",
)
TABLE_HEADERS = {
    "train_s_per_step": "train s/step",
    "train_cost": "train x base",
    "img_per_s": "img/s",
    "inference_cost": "img cost x base",
    "ssim": "SSIM",
    "background_ssim": "bg SSIM",
    "psnr": "PSNR dB",
    "background_psnr": "bg PSNR",
    "contact_ssim": "contact SSIM",
    "background_contact_ssim": "bg contact SSIM",
    "contact_psnr": "contact PSNR dB",
    "background_contact_psnr": "bg contact PSNR",
    "codes_used": "codes used",
    "pareto_front": "Pareto front",
}


def render_markdown(result: dict[str, Any]) -> list[str]:
    """``tradeoff.md``: what was measured, the one table and how to read it."""
    seeds, settings = len(result["seeds"]), result["settings"]
    drift = [row for row in result["summary"] if row["setting"] == DRIFT]
    lines = [
        f"# Speed/accuracy trade of the whole pipeline ({seeds} seeds: mean ± std)",
        "",
        f"Baseline: scene `{result['scene']}`{'' if settings['full'] else ' scaled like `vqtouch demo`'}; "
        f"tokenizer {result['baseline']}, {settings['tokenizer_steps']} training steps per tokenizer"
        + (
            f"; generator {settings['generator_steps']} steps on the baseline tokenizer's codes, sampling "
            f"{result['generator_baseline']}"
            if result["generator_baseline"]
            else ""
        )
        + ".",
        "",
        f"Costs: `train s/step` is the median of {settings['rounds']} interleaved rounds of "
        f"{settings['timing_steps']} training steps; `img/s` encodes and decodes held-out images (tokenizer) or "
        "encodes the condition, samples and decodes (generator: the whole pipeline's cost of a generated image); "
        "`x base` is the ratio to the baseline timed in the same process, per seed, then averaged.  The "
        f"`{DRIFT}` rows time the baseline again at the end of every round: their `x base` is the machine's "
        "drift, the error bar of every ratio.",
        "",
        "Quality on the held-out split: `bg` is the data's no-contact image scored the same way (a model that "
        "draws only the background gets it); `contact` scores only the pixels in contact.  The Pareto fronts "
        "(training and inference cost of the tokenizers, generation cost of the samplings) use "
        f"{FRONT_TEXT[result['front_quality']]}.",
        "",
    ]
    lines += markdown_table(result["summary"], ("part", "knob", "setting"), TABLE_KEYS, TABLE_HEADERS)
    notes = []
    if any(row["knob"] == "resolution" for row in result["summary"]):
        notes.append(
            "The resolution rows are scored at their own resolution (the same scenes rendered larger): "
            "their quality is not the same measurement as the other rows'."
        )
    for row in drift:
        for key in ("train_cost", "inference_cost"):
            if isinstance(row.get(key), float) and abs(row[key] - 1) > 0.1:
                notes.append(
                    f"The {row['part']} baseline's {key.replace('_', ' ')} drifted by "
                    f"{100 * (row[key] - 1):+.0f}% within a round: ratios closer to 1 than that are noise."
                )
    if notes:
        lines += ["", *notes]
    return lines


def plot_tradeoff(summary: list[dict[str, Any]], key: str, path: Path, title: str) -> None:
    """``tradeoff.png``: one panel per front (tokenizer training cost, tokenizer inference cost,
    generation cost; relative to the baseline, log scale) against the contact score, error bars the
    std over seeds, each setting labelled, the front a line, the no-contact image's score dashed."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    panels = [
        (part, cost, name)
        for part, cost, name in FRONTS
        if any(row["part"] == part and isinstance(row.get(key), (int, float)) for row in summary)
    ]
    figure = Figure(figsize=(5.5 * max(len(panels), 1), 4.6), layout="constrained")
    FigureCanvasAgg(figure)
    label = AXIS_LABELS[key]
    axis_names = {
        "training": "tokenizer training s/step",
        "inference": "tokenizer encode + decode s/image",
        "generation": "generation (sample + decode) s/image",
    }
    for number, (part, cost, name) in enumerate(panels):
        axes = figure.add_subplot(1, len(panels), number + 1)
        rows = [
            row
            for row in summary
            if row["part"] == part
            and row["setting"] != DRIFT
            and isinstance(row.get(key), (int, float))
            and isinstance(row.get(cost), (int, float))
        ]
        axes.errorbar(
            [row[cost] for row in rows],
            [row[key] for row in rows],
            xerr=[row.get(f"{cost}_std", 0) for row in rows],
            yerr=[row.get(f"{key}_std", 0) for row in rows],
            fmt="o",
            markersize=4,
            capsize=2,
            color="tab:blue",
            zorder=3,
        )
        for row in rows:
            text = "baseline" if row["knob"] == "baseline" else f"{row['knob']}: {row['setting']}"
            axes.annotate(text, (row[cost], row[key]), textcoords="offset points", xytext=(4, 3), fontsize=7)
        front = sorted((row for row in rows if name in row["pareto"]), key=lambda row: row[cost])
        axes.plot(
            [row[cost] for row in front],
            [row[key] for row in front],
            color="tab:red",
            linewidth=1.5,
            label="Pareto front",
            zorder=2,
        )
        base = next((row for row in rows if row["knob"] == "baseline"), None)
        if base is not None and isinstance(base.get(f"background_{key}"), (int, float)):
            axes.axhline(base[f"background_{key}"], linestyle="--", color="grey", linewidth=1, label="no-contact image")
        axes.set_xscale("log")
        # Ratios span less than a decade: label 0.5x, 1x, 2x ... rather than powers of ten.
        axes.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
        axes.xaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}x"))
        axes.xaxis.set_minor_formatter(NullFormatter())
        axes.set_xlabel(f"{axis_names[name]}, x baseline (log scale)")
        axes.set_ylabel(f"{label} (higher is better)")
        axes.set_title(f"{part} knobs: {name} cost", fontsize=9)
        axes.grid(True, which="both", alpha=0.3)
        axes.legend(fontsize=7)
    figure.suptitle(title, fontsize=9)
    figure.savefig(path, dpi=120)

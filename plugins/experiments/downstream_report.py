"""What ``vqtouch evaluate downstream`` writes for people: ``downstream.md``'s table and notes, and the
figures of the scores, the confusion matrices and the generated images
(:mod:`vqtouch.plugins.experiments.downstream`)."""

from __future__ import annotations

import textwrap
from pathlib import Path
from typing import Any, Sequence

import torch

from vqtouch.plugins.evaluation.records import ExperimentRecord, markdown_table
from vqtouch.plugins.generator import RANK_DESCRIPTIONS
from vqtouch.plugins.utils.images import image_grid, save_png

from .downstream_arms import (
    BACKGROUND,
    CEILING,
    FEW,
    FEW_AND_GENERATED,
    FEW_AND_RECONSTRUCTED,
    GENERATED,
    GROUP,
    RECONSTRUCTED,
    SCORES,
)

#: The table's headers where they are not the column's key.
HEADERS = {
    "real_per_class": "real / class",
    "generated_per_class": "generated / class",
    "train_images": "train images",
    "top1": "top-1",
    "f1": "F1",
}


def render_markdown(result: dict[str, Any]) -> list[str]:
    """The table of ``downstream.json`` for people."""
    lines = _introduction(result)
    lines += markdown_table(result["summary"], GROUP, ("train_images", *SCORES), HEADERS)
    return lines + _baselines(result) + _comparisons(result) + _settings_notes(result)


def _introduction(result: dict[str, Any]) -> list[str]:
    """The heading and what was trained, tested and generated."""
    lines = [
        "# Downstream recognition (Table 3)",
        "",
        f"A classifier trained on each arm's images, tested on the run's {result['test_images']} real held-out "
        f"images ({len(result['classes'])} classes, held out by {result['split_unit']}; never trained on).  "
        f"Classifier: {result['classifier']}.  Top-1 accuracy; precision, recall and F1 macro-averaged over the "
        f"test set's classes.  Generated with `{result['conditioner']}`, sampler {result['sampler']}, "
        f"{result['steps']} steps, guidance {result['guidance']:g}.",
        "",
    ]
    if result["real_images"] != "as read":
        lines += [
            "Every real image (training and held-out) and the no-contact image passed through the run's "
            "tokenizer first (--through-tokenizer): real and generated images share the decoder's look.",
            "",
        ]
    return lines


def _ceiling_text(result: dict[str, Any]) -> str:
    """What the ceiling arm trained on: every real training image, or the ``--train-images`` drawn."""
    return (
        "every real training image of the run's split"
        if result["real_train_images"] + result["train_unlabelled"] == result["generator_train_images"]
        else f"{result['real_train_images']} of the run's {result['generator_train_images']} real training "
        "images (--train-images)"
    )


def _baselines(result: dict[str, Any]) -> list[str]:
    """Chance, the majority-class rate, the ceiling and the reconstruction arms the scores compare with."""
    return [
        "",
        f"Chance (1 / {len(result['classes'])} classes): {result['chance']:.4g}.  Majority-class rate "
        f"(always naming the test set's most common class): {result['majority']:.4g}.",
        "",
        f"`{CEILING}` is the ceiling: {_ceiling_text(result)}.  The generator itself was trained on the run's "
        f"{result['generator_train_images']} training images, so `{GENERATED}` measures whether its images carry "
        "the class, not what K real images would teach it.",
        "",
        f"`{RECONSTRUCTED}` and `{FEW_AND_RECONSTRUCTED}`: the generated images replaced by the tokenizer's "
        f"reconstructions of {result['generated_per_class']} other real training images per class, what a "
        "generator that reproduced its training images would give (the generated arms' ceiling).",
    ]


def _comparisons(result: dict[str, Any]) -> list[str]:
    """The CAS ratio, what the generated images add, and the classes short of reconstructions."""
    lines: list[str] = []
    cas, adds = result.get("cas_ratio"), result.get("generated_adds")
    if cas:
        lines += [
            "",
            f"CAS ratio (`{GENERATED}` top-1 over `{FEW}` top-1 at the same {result['shots']} images per class, "
            f"per seed): {cas['mean']:.3f} ± {cas['std']:.3f}.",
        ]
    if adds:
        lines += [
            "",
            f"`{FEW_AND_GENERATED}` minus `{FEW}` (top-1, per seed): {adds['mean']:+.3f} ± {adds['std']:.3f}.",
        ]
    if result["reconstruction_shortfall"]:
        lines += [
            "",
            "Classes with fewer other training images than that (class: reconstructions short): "
            + ", ".join(f"{label}: {count}" for label, count in result["reconstruction_shortfall"].items())
            + ".",
        ]
    return lines


def _settings_notes(result: dict[str, Any]) -> list[str]:
    """Notes on best-of sampling, the background arm, the weighted arms and unlearnable classes."""
    lines: list[str] = []
    if result.get("best_of", 1) > 1:
        rank = result.get("best_of_rank", "judge")
        # A plugin's ranker has no built-in description: it is named.
        ranked_by = RANK_DESCRIPTIONS.get(rank, f"the `{rank}` ranker")
        lines += [
            "",
            f"Each generated image is the best of {result['best_of']} candidates by {ranked_by} "
            "(--best-of, --best-of-rank).",
        ]
    if result["background"]:
        lines += [
            "",
            f"`{BACKGROUND}`: the no-contact image ({result['background']}) as every class's training "
            f"images, what a generator that draws only the background would give `{GENERATED}` (a classifier "
            "that names one class: at most the majority-class rate).  Claim `better` on the real held-out "
            "scores above it.",
        ]
    if result.get("generated_weights", [1.0]) != [1.0]:
        lines += [
            "",
            f"`{FEW_AND_GENERATED} (weight W)`: the same images as `{FEW_AND_GENERATED}`, each generated one "
            "weighing W against 1 for a real image in the classifier's standardization and loss.",
        ]
    if result["classes_without_training_images"]:
        lines += [
            "",
            f"Held-out classes with no training image (no arm can learn them): "
            f"{result['classes_without_training_images']}.",
        ]
    return lines


def save_figures(result: dict[str, Any], shown_N3HW: torch.Tensor, record: ExperimentRecord) -> None:
    """``downstream.png``, ``downstream_confusion.png`` and ``downstream_generated.png`` of ``result``
    (``shown_N3HW``: the first seed's generated images)."""
    confusion = result["confusion"]
    plot_scores(
        result["summary"],
        result["chance"],
        result["majority"],
        record.path("downstream.png"),
        f"downstream recognition on {result['test_images']} real held-out images ({len(record.seeds)} seeds)",
    )
    plot_confusions(
        confusion["matrices"],
        [result["classes"][label] for label in confusion["labels"]],
        record.path("downstream_confusion.png"),
        f"seed {record.seeds[0]}",
    )
    save_generated(shown_N3HW, result["generated_per_class"], record.path("downstream_generated.png"))


def plot_scores(summary: list[dict[str, Any]], chance: float, majority: float, path: Path, title: str) -> None:
    """Grouped bars: the four scores of every arm (mean, standard deviation as error bars), with the
    chance level and the majority-class rate as lines."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(11, 4), dpi=110)
    FigureCanvasAgg(figure)
    axes = figure.add_subplot(1, 1, 1)
    width = 0.8 / len(SCORES)
    for offset, score in enumerate(SCORES):
        positions = [index + (offset - (len(SCORES) - 1) / 2) * width for index in range(len(summary))]
        axes.bar(
            positions,
            [row[score] for row in summary],
            width,
            yerr=[row[f"{score}_std"] for row in summary],
            capsize=3,
            label=score,
        )
    axes.axhline(chance, linestyle="--", color="grey", label="chance")
    axes.axhline(majority, linestyle=":", color="black", label="majority class")
    # Wrapped: with seven or more arms, whole names run into each other.
    axes.set_xticks(range(len(summary)), [textwrap.fill(row["arm"], 16) for row in summary], fontsize=8)
    axes.set_ylim(0, 1.05)
    axes.set_ylabel("score on real held-out images")
    axes.legend(fontsize=7, ncols=3)
    axes.grid(axis="y", alpha=0.3)
    axes.set_title(title, fontsize=9)
    figure.tight_layout()
    figure.savefig(path)


def plot_confusions(confusion: dict[str, list[list[int]]], class_names: Sequence[str], path: Path, title: str) -> None:
    """One row-normalised confusion matrix (true class down, predicted across) per arm."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(3.2 * len(confusion), 3.8), dpi=110)
    FigureCanvasAgg(figure)
    for index, (arm, matrix) in enumerate(confusion.items()):
        counts = torch.tensor(matrix, dtype=torch.float64)
        axes = figure.add_subplot(1, len(confusion), index + 1)
        axes.imshow((counts / counts.sum(dim=1, keepdim=True).clamp_min(1)).numpy(), vmin=0, vmax=1, cmap="Blues")
        axes.set_title(arm, fontsize=8)
        ticks = range(len(class_names))
        size = 7 if len(class_names) <= 12 else 4
        axes.set_xticks(ticks, class_names, rotation=90, fontsize=size)
        axes.set_yticks(ticks, class_names if index == 0 else [""] * len(class_names), fontsize=size)
    figure.suptitle(
        f"confusion on the real held-out images ({title}; rows: true class, columns: predicted)", fontsize=9
    )
    figure.tight_layout()
    figure.savefig(path, bbox_inches="tight")  # rotated class names reach below the axes


def save_generated(images_N3HW: torch.Tensor, per_class: int, path: Path) -> None:
    """The generated images, one row per class (at most 8 a row)."""

    shown = min(per_class, 8)
    rows = images_N3HW.view(-1, per_class, *images_N3HW.shape[1:])[:, :shown]
    save_png(image_grid(rows.reshape(-1, *images_N3HW.shape[1:]), columns=shown), path)

"""A stage result's scores against their comparisons: the score table (a key ``P + X`` beside ``X``
is the comparison ``P``'s score ``X``, see :data:`COMPARISON_PREFIXES`) and the verdict on the
contact region (:func:`contact_verdict`), shared by report.md and report.html."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from vqtouch.plugins.evaluation.contact import (
    OUTPUT_SPREAD_KEY,
    VERDICT_BASELINE_PREFIXES,
    gap_interval_key,
)
from vqtouch.plugins.evaluation.directions import lower_is_better

from .results import PARTS_KEY, PICTURE_KEYS, format_value, is_skip_key


#: Result-key prefixes that name a comparison, in column order: a key ``P + X`` where ``X`` is also a
#: key of the result (``background_psnr`` next to ``psnr``) is the score ``X`` of the comparison ``P``,
#: shown in P's column beside the model's own ``X``.  Values: what each comparison is (a header tooltip).
COMPARISON_PREFIXES = {
    "background_": "the no-contact background image: the rendering sensor's, or the per-pixel median of captured "
    "training frames (what a model that draws only the background scores)",
    "ceiling_": "the tokenizer's own reconstruction of the ground truth (no generator over its codes does better)",
    "retrieval_": "the nearest training image by condition",
    "class_mean_": "the mean training image of the condition's class",
    "real_": "the real held-out images themselves",
    "before_": "the same model before it was adapted (the family tokenizer, for an adapted one)",
}

#: The comparison every model score must beat: tactile images are mostly static background, so a
#: whole-image score flatters a model that draws only that.
BACKGROUND_PREFIX = "background_"

#: The contact-region scores a verdict is given on, first found first: (score, how it is named, unit).
CONTACT_VERDICT_SCORES = (("contact_psnr", "contact PSNR", " dB"), ("contact_mae", "contact MAE", ""))


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _is_score_value(value: Any) -> bool:
    # A score is a number (None where it could not be computed); counts, names and nested tables are facts.
    return value is None or (isinstance(value, (int, float)) and not isinstance(value, bool))


def beats(score: str, model: Any, baseline: Any) -> bool | None:
    """Whether ``model``'s value of ``score`` is strictly better than ``baseline``'s (a tie is not), in
    the score's direction (:func:`lower_is_better`); None when either is not a finite number."""
    if not (_is_number(model) and _is_number(baseline)):
        return None
    return model < baseline if lower_is_better(score) else model > baseline


@dataclass(frozen=True)
class ScoreTable:
    """A stage result split for display: ``rows`` maps each score that has a comparison to its values by
    prefix (``""`` for the model's own, then the :data:`COMPARISON_PREFIXES` present), ``columns`` are
    the comparison prefixes present (in that order) and ``facts`` everything else but the pictures."""

    rows: dict[str, dict[str, Any]]
    columns: tuple[str, ...]
    facts: dict[str, Any]


def score_table(result: Mapping[str, Any]) -> ScoreTable:
    """Split ``result`` into the scores with comparisons (a key ``P + X`` beside a key ``X``, ``P`` one of
    :data:`COMPARISON_PREFIXES`, both numbers) and the other facts, keeping the result's order."""
    scores = {
        key: value
        for key, value in result.items()
        if key not in PICTURE_KEYS and key != PARTS_KEY and not is_skip_key(key) and _is_score_value(value)
    }
    rows: dict[str, dict[str, Any]] = {}
    for key in scores:
        compared = {prefix: scores[prefix + key] for prefix in COMPARISON_PREFIXES if prefix + key in scores}
        if compared:
            rows[key] = {"": scores[key], **compared}
    paired = {prefix + key for key, values in rows.items() for prefix in values}
    columns = tuple(prefix for prefix in COMPARISON_PREFIXES if any(prefix in values for values in rows.values()))
    facts = {
        key: value
        for key, value in result.items()
        if key not in PICTURE_KEYS and key != PARTS_KEY and key not in paired
    }
    return ScoreTable(rows, columns, facts)


#: The baselines a verdict weighs, strongest first found: what drawing without the model gets.
VERDICT_BASELINES = dict(
    zip(
        VERDICT_BASELINE_PREFIXES,
        ("the no-contact background", "retrieval of the nearest training image", "the class-mean training image"),
        strict=True,
    )
)
#: The least gap that counts as better, per verdict score: under it a model is "no better than" its
#: strongest baseline however steady the gap (0.5 dB of contact PSNR is about a 12% lower squared
#: error on the contact; for a mean absolute error, 5% of the baseline's).
MIN_VERDICT_GAP = {"contact_psnr": 0.5, "contact_mae": 0.05}
MIN_VERDICT_GAP_TEXT = {"contact_psnr": "0.5 dB", "contact_mae": "5%"}
#: A model whose outputs vary across inputs less than this share of the real images' variation
#: (``output_spread_ratio``) draws about the same image whatever its input: it gets no verdict of
#: better, whatever its scores.
IGNORES_INPUT_BELOW = 0.2


def contact_verdict(result: Mapping[str, Any]) -> tuple[bool, str] | None:
    """Whether the model clearly beats every baseline on the contact region, and a sentence saying
    so with the numbers, from the first of :data:`CONTACT_VERDICT_SCORES` the result has with its
    no-contact background; None when it has none.

    Better (True) needs all of: outputs that are not near-constant (``output_spread_ratio`` at least
    :data:`IGNORES_INPUT_BELOW`, when measured), a gap to the strongest baseline present
    (:data:`VERDICT_BASELINES`) of at least :data:`MIN_VERDICT_GAP`, and, when measured, a 95%
    bootstrap interval of the contact PSNR gap over images whose low end clears that minimum too.
    Otherwise the sentence says which failed: "ignores its input", "no better than ... within noise"
    or "worse".  (``input_correlation`` is reported, not ruled on: a label-conditioned generator,
    which must invent the pose, correlates with its truths as little as an unrelated output does.)"""
    spread = result.get(OUTPUT_SPREAD_KEY)
    for score, name, unit in CONTACT_VERDICT_SCORES:
        model = result.get(score)
        present = {
            prefix: result[prefix + score]
            for prefix in VERDICT_BASELINES
            if beats(score, model, result.get(prefix + score)) is not None
        }
        if BACKGROUND_PREFIX not in present:
            continue
        lower = lower_is_better(score)
        strongest = (min if lower else max)(present, key=lambda prefix: present[prefix])
        baseline = present[strongest]
        gap = baseline - model if lower else model - baseline
        fraction = result.get("contact_fraction")
        share = ""
        if _is_number(fraction):
            share = f" ({fraction:.1%} of pixels)" if 0 < fraction < 0.01 else f" ({fraction:.0%} of pixels)"
        shown = [f"{value:.2f}" if unit == " dB" else format_value(value) for value in (model, baseline)]
        numbers = f"{name} {shown[0]} vs {shown[1]}{unit}"
        against = VERDICT_BASELINES[strongest]
        if strongest != BACKGROUND_PREFIX:
            against += " (the strongest baseline here)"
        if _is_number(spread) and spread < IGNORES_INPUT_BELOW:
            return False, (
                f"The model ignores its input: its outputs vary across inputs {spread:.0%} as much as the "
                f"real images do (under {IGNORES_INPUT_BELOW:.0%}), so no score of it means much; on the "
                f"contact region{share} {numbers} for {against}."
            )
        low = result.get(gap_interval_key(strongest, "low")) if score == "contact_psnr" else None
        high = result.get(gap_interval_key(strongest, "high")) if score == "contact_psnr" else None
        interval = ""
        if _is_number(low) and _is_number(high):
            interval = f"; 95% interval of the gap over images {low:+.2f} to {high:+.2f} dB"
        minimum = MIN_VERDICT_GAP[score] * (abs(baseline) if lower else 1.0)
        if gap <= 0:
            comparison = "worse than" if gap < 0 else "no better than"
            return False, f"On the contact region{share} the model is {comparison} {against}: {numbers}{interval}."
        if gap < minimum or (_is_number(low) and low < minimum):
            reason = (
                f"a gap under the {MIN_VERDICT_GAP_TEXT[score]} minimum"
                if gap < minimum
                else f"another draw of held-out images could bring the gap under the {MIN_VERDICT_GAP_TEXT[score]} "
                "minimum"
            )
            return False, (
                f"On the contact region{share} the model is no better than {against} within noise: {numbers}, "
                f"{reason}{interval}."
            )
        return True, f"On the contact region{share} the model is better than {against}: {numbers}{interval}."
    return None

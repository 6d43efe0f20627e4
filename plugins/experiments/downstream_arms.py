"""The arms of ``vqtouch evaluate downstream`` (:mod:`vqtouch.plugins.experiments.downstream`): their
names, the real images each draws, the features they train on and the scores compared across them."""

from __future__ import annotations

import dataclasses
import math
import statistics
from typing import Any, Callable, Sequence

import torch

from vqtouch.core import ConfigError

GENERATED, FEW, FEW_AND_GENERATED, CEILING, RECONSTRUCTED, FEW_AND_RECONSTRUCTED, BACKGROUND = (
    "generated only",
    "real few",
    "real few + generated",
    "all real (ceiling)",
    "reconstructions only",
    "real few + reconstructions",
    "no-contact background",
)
#: The arms in table order: the tokenizer's reconstructions stand in for a generator that reproduced
#: its training images (the ceiling of the two generated arms); the background row last, the floor of
#: ``generated only``.
ARMS = (GENERATED, FEW, FEW_AND_GENERATED, CEILING, RECONSTRUCTED, FEW_AND_RECONSTRUCTED, BACKGROUND)
#: The recognition scores of each arm, all in [0, 1].
SCORES = ("top1", "precision", "recall", "f1")
#: How the table groups the rows (the seeds of one group are averaged).
GROUP = ("arm", "real_per_class", "generated_per_class")


@dataclasses.dataclass
class LabelledFeatures:
    """Frozen-network features of labelled images: ``features_NF`` (N, F), their ``labels`` and the
    dataset ``indices`` they came from (empty for images that are not in the dataset)."""

    features_NF: torch.Tensor
    labels: list[int]
    indices: list[int]

    def take(self, positions: Sequence[int]) -> LabelledFeatures:
        """The rows at ``positions``."""
        positions = list(positions)
        return LabelledFeatures(
            self.features_NF[positions],
            [self.labels[p] for p in positions],
            [self.indices[p] for p in positions] if self.indices else [],
        )

    @staticmethod
    def join(*parts: LabelledFeatures) -> LabelledFeatures:
        """The rows of every part, in order."""
        return LabelledFeatures(
            torch.cat([part.features_NF for part in parts]),
            [label for part in parts for label in part.labels],
            [index for part in parts for index in part.indices],
        )


def recognition_scores(true_labels: Sequence[int], predicted: Sequence[int]) -> dict[str, float]:
    """``top1`` accuracy and the ``precision``, ``recall`` and ``f1`` macro-averaged over the classes
    of ``true_labels`` (scikit-learn; a class never predicted has precision 0, and the macro F1 is the
    mean of the per-class F1s, not the F1 of the macro precision and recall)."""
    from sklearn.metrics import accuracy_score, precision_recall_fscore_support

    precision, recall, f1, _ = precision_recall_fscore_support(
        true_labels, predicted, labels=sorted(set(true_labels)), average="macro", zero_division=0
    )
    return {
        "top1": round(float(accuracy_score(true_labels, predicted)), 4),
        "precision": round(float(precision), 4),
        "recall": round(float(recall), 4),
        "f1": round(float(f1), 4),
    }


def _positions_by_class(labels: Sequence[int], exclude: Sequence[int] = ()) -> dict[int, list[int]]:
    """Class -> its positions in ``labels``, in order, leaving out those in ``exclude``."""
    excluded = set(exclude)
    by_class: dict[int, list[int]] = {}
    for position, label in enumerate(labels):
        if position not in excluded:
            by_class.setdefault(label, []).append(position)
    return by_class


def _draw_per_class(by_class: dict[int, list[int]], count: int, seed: int) -> list[int]:
    """Up to ``count`` positions of every class (in class order), drawn without replacement by ``seed``."""
    draw = torch.Generator().manual_seed(seed)
    chosen = []
    for label in sorted(by_class):
        members = by_class[label]
        chosen += [members[i] for i in torch.randperm(len(members), generator=draw)[:count].tolist()]
    return chosen


def draw_shots(labels: Sequence[int], shots: int, seed: int, class_names: Sequence[str] = ()) -> list[int]:
    """Positions of ``shots`` images of every class in ``labels``, drawn without replacement by
    ``seed``; a one-line ConfigError naming the class when one has fewer."""
    by_class = _positions_by_class(labels)
    scarcest = min(by_class, key=lambda label: (len(by_class[label]), label))
    if len(by_class[scarcest]) < shots:
        name = f"{class_names[scarcest]!r} ({scarcest})" if scarcest < len(class_names) else str(scarcest)
        raise ConfigError(
            f"--shots {shots}: class {name} has only {len(by_class[scarcest])} real training images in "
            f"the run's split; give --shots {len(by_class[scarcest])} or fewer"
        )
    return _draw_per_class(by_class, shots, seed)


def draw_others(labels: Sequence[int], per_class: int, seed: int, exclude: Sequence[int]) -> list[int]:
    """Positions of up to ``per_class`` images of every class in ``labels`` outside ``exclude``, drawn
    without replacement by ``seed`` (all the others of a class that has fewer): the training images
    whose reconstructions stand in for a perfect generator's ``per_class`` images of the class."""
    # Its own stream, so that the reconstructions never shift the shots or the generated images.
    return _draw_per_class(_positions_by_class(labels, exclude), per_class, seed * 1_000_003 + 7)


def paired_over_seeds(
    rows: Sequence[dict[str, Any]], arm: str, rival: str, combine: Callable[[float, float], float]
) -> dict[str, float] | None:
    """``combine(arm's top-1, rival's top-1)`` per seed, as ``{"mean", "std"}`` over the seeds where both
    arms trained (None where none did)."""
    by_seed = {(row["arm"], row["seed"]): row["top1"] for row in rows}
    values = [
        combine(by_seed[(arm, seed)], by_seed[(rival, seed)])
        for seed in sorted({row["seed"] for row in rows})
        if (arm, seed) in by_seed and (rival, seed) in by_seed
    ]
    values = [value for value in values if math.isfinite(value)]
    if not values:
        return None
    # The population spread, as the summary's (mean_spread).
    return {"mean": round(statistics.fmean(values), 4), "std": round(statistics.pstdev(values), 4)}


def classification_accuracy_score(rows: Sequence[dict[str, Any]], shots: int, generated_per_class: int) -> Any:
    """The field's CAS ratio (Ravuri and Vinyals, 2019): top-1 of the classifier trained on generated
    images only over that of the same classifier trained on as many real images, per seed; None
    unless ``shots`` equals ``generated_per_class`` (the counts must match)."""
    if shots != generated_per_class:
        return None
    return paired_over_seeds(rows, GENERATED, FEW, lambda generated, real: generated / real if real else math.nan)


def mixed_arm(generated_weight: float) -> str:
    """The name of the ``real few + generated`` arm whose generated images weigh ``generated_weight``
    against 1 for a real image (the plain name at weight 1)."""
    return FEW_AND_GENERATED if generated_weight == 1.0 else f"{FEW_AND_GENERATED} (weight {generated_weight:g})"


def check_generated_weights(weights: Sequence[float]) -> list[float]:
    """``weights`` as floats; a one-line ConfigError for none, a repeat, or one that is not a finite
    number > 0 (a weight of 0 is the ``real few`` arm)."""
    weights = [float(weight) for weight in weights]
    if not weights:
        raise ConfigError("--generated-weight: give at least one weight (1: a generated image counts as a real one)")
    for weight in weights:
        if not (math.isfinite(weight) and weight > 0):
            raise ConfigError(
                f"--generated-weight {weight:g}: must be a finite number > 0 (weight 0 is the `{FEW}` arm)"
            )
    if len({mixed_arm(weight) for weight in weights}) != len(weights):
        raise ConfigError(f"--generated-weight {' '.join(f'{w:g}' for w in weights)}: each weight once")
    return weights

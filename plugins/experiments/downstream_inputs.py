"""What the arms of ``vqtouch evaluate downstream`` draw from (:mod:`vqtouch.plugins.experiments.downstream`):
the experiment's settings, the run's labelled data and split, and the frozen-network features of its
real, held-out and no-contact images."""

from __future__ import annotations

import dataclasses
import time
from typing import Any, Callable, Sequence

import torch

from vqtouch.core import Assembly, ConfigError, PluginHost
from vqtouch.plugins.evaluation.contact import dataset_background
from vqtouch.plugins.utils.splits import experiment_split

from .downstream_arms import LabelledFeatures, draw_shots

#: Real images read and featurized at a time.
FEATURE_CHUNK = 64


@dataclasses.dataclass(frozen=True)
class ArmSettings:
    """What the arms train on: real and generated images per class, the mixed arms' weights of a
    generated image, the side the feature network sees, the real training images featurized (0:
    all) and whether the real images pass through the tokenizer first."""

    shots: int = 5
    generated_per_class: int = 10
    generated_weights: tuple[float, ...] = (1.0,)
    feature_size: int | None = None
    train_images: int = 0
    through_tokenizer: bool = False


@dataclasses.dataclass(frozen=True)
class SamplingSettings:
    """How the generated arms' images are drawn, resolved against the run's generator: its label
    ``conditioner`` (and its ``index:name``), the sampler, steps, guidance, labels per forward pass
    and the best-of choice."""

    conditioner: Any
    conditioner_label: str
    sampler: Any
    sampler_name: str
    steps: int
    guidance: float
    batch_size: int
    best_of: int
    best_of_rank: str


@dataclasses.dataclass(frozen=True)
class LabelledData:
    """The run's labelled dataset, its class names and the generator's split of it."""

    assembly: Any
    dataset: Any
    name: str
    class_names: list[str]
    train_split: Any
    test_split: Any


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


def feature_metric(config: Any, assembly: Any, feature_size: int | None) -> Any:
    """The ``fd_effnetlite0`` metric whose network gives the features: ``feature_size`` when given,
    else the run's own ``fd_effnetlite0`` metric's size, else 224."""
    if feature_size is None:
        feature_size = next((item.image_size for item in config.metrics if item.name == "fd_effnetlite0"), 224)
    return assembly.build("metric", {"name": "fd_effnetlite0", "image_size": feature_size})


def labelled_data(config: Any, host: PluginHost) -> LabelledData:
    """The run's dataset and its split; a one-line ConfigError for a dataset without class labels or
    a run that holds out no images."""
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
    return LabelledData(assembly, dataset, dataset_name, class_names, train_split, test_split)


def reconstruction(tokenizer: Any) -> Callable[[torch.Tensor], torch.Tensor]:
    """The ``tokenizer``'s reconstruction (encoded and decoded) of a chunk of images, on the CPU."""
    from vqtouch.plugins.tokenizer import reconstruct_all

    def reconstruct(images_N3HW: torch.Tensor) -> torch.Tensor:
        return reconstruct_all(tokenizer, images_N3HW.to(tokenizer.device), FEATURE_CHUNK).float().cpu()

    return reconstruct


def training_pool(train_split: Any, train_images: int) -> list[int]:
    """The real training images to featurize: all of ``train_split``, or ``train_images`` of them
    drawn once (the same draw for every seed)."""
    pool = list(train_split.indices)
    if train_images and train_images < len(pool):
        order = torch.randperm(len(pool), generator=torch.Generator().manual_seed(0)).tolist()
        pool = sorted(pool[i] for i in order[:train_images])
    return pool


def check_labels(classes: Sequence[int], test: LabelledFeatures, data: LabelledData) -> None:
    """A one-line ConfigError for fewer than two training classes or no labelled held-out image."""
    if len(classes) < 2:
        raise ConfigError(
            f"the run's training split holds {len(classes)} labelled class(es) of {data.name}; "
            "a classifier needs at least 2"
        )
    if not test.labels:
        raise ConfigError(
            f"none of the run's {len(data.test_split)} held-out images of {data.name} has a label; "
            "downstream recognition tests on labelled held-out images"
        )


def background_features(
    data: LabelledData, metric: Any, prepare: Callable[[torch.Tensor], torch.Tensor] | None
) -> tuple[torch.Tensor | None, Any]:
    """The features (1, F) of the training images' no-contact image (None without one) and how it
    was made."""
    background, source = dataset_background(data.train_split, tuple(data.test_split[0]["tactile"].shape[-2:]))
    if background is not None and prepare is not None:
        background = prepare(background[None])[0]
    return (None if background is None else metric.pooled_features(background[None]).float()), source


@dataclasses.dataclass(frozen=True)
class RealImages:
    """The features of the real training images (and how many were unlabelled), of the held-out
    images, and of the no-contact image (None without one) with how it was made; the training
    images' classes and every class of either split."""

    train: LabelledFeatures
    train_unlabelled: int
    test: LabelledFeatures
    test_unlabelled: int
    background_features: torch.Tensor | None
    background_source: Any
    classes: list[int]
    every_class: list[int]


def featurize_real(
    data: LabelledData,
    metric: Any,
    arms: ArmSettings,
    reconstruct: Callable[[torch.Tensor], torch.Tensor],
    report: Callable[[str], None],
) -> RealImages:
    """The features of the real training, held-out and no-contact images (through ``reconstruct``
    with ``arms.through_tokenizer``), checked to hold two classes, labelled held-out images and the
    shots asked for, before anything is generated."""
    prepare = reconstruct if arms.through_tokenizer else None
    tic = time.perf_counter()
    real_train, train_unlabelled = real_features(
        data.dataset, training_pool(data.train_split, arms.train_images), metric, prepare
    )
    test, test_unlabelled = real_features(data.dataset, data.test_split.indices, metric, prepare)
    report(
        f"features of {len(real_train.labels)} real training and {len(test.labels)} held-out images"
        f"{' (through the tokenizer)' if arms.through_tokenizer else ''} at {metric.image_size} px in "
        f"{time.perf_counter() - tic:.0f} s"
    )
    classes = sorted(set(real_train.labels))
    check_labels(classes, test, data)
    # Too many shots are refused here, before anything is generated.
    draw_shots(real_train.labels, arms.shots, 0, data.class_names)
    features, source = background_features(data, metric, prepare)
    return RealImages(
        real_train,
        train_unlabelled,
        test,
        test_unlabelled,
        features,
        source,
        classes,
        sorted(set(classes) | set(test.labels)),
    )

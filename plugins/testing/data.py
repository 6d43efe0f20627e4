"""The behaviour of the data-side base classes: clusterers, metrics and datasets."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch

from vqtouch.core.components import (
    BuildContext,
    Clusterer,
    Metric,
    TactileDataset,
)
from vqtouch.core.image_size import ImageSize, image_hw, size_text
from ._support import DEFAULT_CONTEXT, OPTIONAL_SAMPLE_KEYS, SAMPLE_KEYS, _call, _close, _features, _generator, _require

if TYPE_CHECKING:
    pass


def check_clusterer(clusterer: Clusterer, context: BuildContext | None = None, *, label: str = "clusterer") -> None:
    """A clusterer's ``fit`` and ``predict`` return one integer cluster index per feature row."""
    features = _features()
    with torch.no_grad():
        fitted = _call(label, "fit(features)", lambda: clusterer.fit(features))
        predicted = _call(label, "predict(features)", lambda: clusterer.predict(features))
    for what, value in (("fit", fitted), ("predict", predicted)):
        _require(
            isinstance(value, torch.Tensor)
            and tuple(value.shape) == (len(features),)
            and not value.dtype.is_floating_point,
            label,
            f"{what} of ({len(features)}, F) features must return ({len(features)},) integer indices, got "
            f"{getattr(value, 'dtype', type(value).__name__)} {tuple(getattr(value, 'shape', ()))}",
        )


def check_metric(metric: Metric, context: BuildContext | None = None, *, label: str = "metric") -> None:
    """A metric scores identical images strictly better than noisy ones (``higher_is_better`` says
    which way), returns a finite float, accumulates every ``update`` and forgets on ``reset``.

    A metric built as skipped (``metric.skipped``: a file or package it needs is missing) must say
    why in a message that names what to provide; its behaviour cannot be checked here, so check
    it again with its weights (the built-ins' suite does, with files of the real layout)."""
    context = context or DEFAULT_CONTEXT
    _require(isinstance(metric.higher_is_better, bool), label, "higher_is_better must be a bool")
    if metric.skipped is not None:
        _require(
            isinstance(metric.skipped, str) and len(metric.skipped.strip()) >= 20,
            label,
            f"a skipped metric must say what is missing and how to provide it, got {metric.skipped!r}",
        )
        return
    # Smooth images (random 4x4 colour fields, upsampled): white noise plus noise is still white noise,
    # which a metric comparing image *sets* (FID, KID) rightly cannot tell apart.
    coarse = torch.rand(4, 3, 4, 4, generator=_generator(2))
    target = torch.nn.functional.interpolate(
        coarse, size=image_hw(context.image_size), mode="bilinear", align_corners=False
    )
    noisy = (target + 0.2 * torch.randn(target.shape, generator=_generator(3))).clamp(0, 1)

    def score(*pairs: tuple[torch.Tensor, torch.Tensor]) -> float:
        metric.reset()
        for predicted, reference in pairs:
            _call(label, "update", lambda p=predicted, r=reference: metric.update(p, r))
        value = _call(label, "compute", metric.compute)
        _require(
            isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value),
            label,
            f"compute() must return a finite float, got {value!r}",
        )
        return float(value)

    same = score((target, target))
    worse = score((noisy, target))
    better = same > worse if metric.higher_is_better else same < worse
    _require(
        better,
        label,
        f"identical images score {same:.6g} and noisy ones {worse:.6g}: identical images must "
        f"score the best value ({'higher' if metric.higher_is_better else 'lower'} is better)",
    )
    _require(
        _close(score((target, target)), same),
        label,
        "after reset(), identical images score differently than the first time: reset() must forget "
        "everything seen (and compute must be deterministic)",
    )
    mixed = score((target, target), (noisy, target))
    _require(not _close(mixed, same), label, "a second update() did not change the result: every update must count")
    _require(not _close(mixed, worse), label, "a second update() replaced the first: updates must accumulate")
    metric.reset()


def check_dataset(dataset: TactileDataset, image_size: ImageSize | None = None, *, label: str = "dataset") -> None:
    """A dataset is non-empty and every sample is a dict with the documented entries: ``tactile``
    (3, H, W) float in [0, 1] (and an optional ``visual`` of the same shape), an int ``label`` in
    [-1, num_classes), str ``text``, non-empty str ``sensor`` and ``id`` (further entries are
    allowed); reading a sample twice gives the same sample and ``context_facts`` reports the class
    count.  ``image_size``: the S or (H, W) samples must have (None: any)."""
    length = _call(label, "len(dataset)", lambda: len(dataset))
    _require(isinstance(length, int) and length > 0, label, f"len(dataset) must be a positive int, got {length!r}")
    names = dataset.class_names
    _require(
        isinstance(names, list) and all(isinstance(n, str) for n in names), label, "class_names must be a list of str"
    )
    _require(
        dataset.context_facts().get("num_classes") == len(names),
        label,
        f"context_facts() must report num_classes={len(names)} (len(class_names))",
    )
    for index in sorted({0, length - 1}):
        sample = _call(label, f"dataset[{index}]", lambda i=index: dataset[i])
        where = f"sample {index}"
        _require(isinstance(sample, dict), label, f"{where} is a {type(sample).__name__}, not a dict")
        missing = [key for key in SAMPLE_KEYS if key not in sample]
        _require(
            not missing,
            label,
            f"{where} lacks {missing} (every sample has {', '.join(SAMPLE_KEYS)}; visual is optional)",
        )
        tactile = sample["tactile"]
        _require(
            isinstance(tactile, torch.Tensor)
            and tactile.dtype.is_floating_point
            and tactile.ndim == 3
            and tactile.shape[0] == 3,
            label,
            f"{where}: tactile must be a float tensor (3, H, W), got "
            f"{getattr(tactile, 'dtype', type(tactile).__name__)} {tuple(getattr(tactile, 'shape', ()))}",
        )
        if image_size is not None:
            _require(
                tuple(tactile.shape[-2:]) == image_hw(image_size),
                label,
                f"{where}: tactile is {tactile.shape[-2]}x{tactile.shape[-1]} px but the experiment's image "
                f"size is {size_text(image_size)}",
            )
        for key in ("tactile", *(k for k in OPTIONAL_SAMPLE_KEYS if k in sample)):
            image = sample[key]
            _require(
                isinstance(image, torch.Tensor) and tuple(image.shape) == tuple(tactile.shape),
                label,
                f"{where}: {key} must have the tactile image's shape {tuple(tactile.shape)}",
            )
            _require(
                bool(torch.isfinite(image).all()) and float(image.min()) >= 0 and float(image.max()) <= 1,
                label,
                f"{where}: {key} has values outside [0, 1]",
            )
        value = sample["label"]
        _require(
            type(value) is int and -1 <= value < len(names) and (names or value == -1),
            label,
            f"{where}: label must be an int in [-1, {len(names)}) (-1: none), got {value!r}",
        )
        _require(isinstance(sample["text"], str), label, f"{where}: text must be a str")
        for key in ("sensor", "id"):
            _require(
                isinstance(sample[key], str) and bool(sample[key]), label, f"{where}: {key} must be a non-empty str"
            )
        again = _call(label, f"dataset[{index}] again", lambda i=index: dataset[i])
        _require(
            again["id"] == sample["id"] and torch.equal(again["tactile"], tactile),
            label,
            f"reading sample {index} twice gave different samples",
        )

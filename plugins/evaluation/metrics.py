"""Pairwise image metrics through torchmetrics, the library the tactile-generation papers use.

- ``psnr``, ``ssim`` and ``ms_ssim`` run torchmetrics' functional implementations in float64, one
  value per image pair (the metric is their mean), or, for the published protocol's PSNR, one
  value of the pooled squared error over every pixel (torchmetrics' default reduction).
- ``lpips`` is torchmetrics' LPIPS network (VGG16 or AlexNet trunk, with the LPIPS v0.1 linear
  heads that ship inside torchmetrics) holding the ImageNet trunk weights from a file the user
  supplies.  Without that file (or without torchvision) it is built as a
  :class:`~vqtouch.core.SkippedMetric` naming the file: reported as skipped, never replaced.

Every metric takes RGB batches (B, 3, H, W) in [0, 1] of equal shape and refuses NaN/Inf.

torchmetrics is imported when a metric first scores, not when it is built: importing it takes
seconds and, when they are installed, imports torchvision and torch-fidelity too.
"""

from __future__ import annotations

from typing import Any

import torch

from vqtouch.core import BuildContext, MissingWeightsError, PerImageMetric, SkippedMetric
from vqtouch.plugins.utils.weights import WeightsSpec, resolve_weights
from vqtouch.core.components import Metric

from .feature_networks import ALEXNET_WEIGHTS
from .metrics_plugin import LpipsConfig, MsSsimConfig, PsnrConfig, SsimConfig  # noqa: F401 - re-exported


def check_pair(predicted: torch.Tensor, target: torch.Tensor, metric: str = "metrics") -> None:
    """Raise ValueError unless ``predicted`` and ``target`` are finite image batches of one shape (B, C, H, W)."""
    if predicted.shape != target.shape or predicted.ndim != 4:
        raise ValueError(
            f"{metric} need two image batches of equal shape (B, C, H, W); got "
            f"{tuple(predicted.shape)} and {tuple(target.shape)}"
        )
    for name, images in (("predicted", predicted), ("target", target)):
        if not torch.isfinite(images).all():
            raise ValueError(f"{name} images contain NaN or Inf")


# -- PSNR -----------------------------------------------------------------------------------------


class Psnr(Metric):
    """Peak signal-to-noise ratio in dB (torchmetrics, float64): per image then averaged, or of the pooled error."""

    higher_is_better = True

    def __init__(self, data_range: float = 1.0, pooled: bool = False, max_db: float = 100.0) -> None:
        self.data_range, self.pooled, self.max_db = data_range, pooled, max_db
        self._pooled: Any = None
        self.reset()

    def update(self, predicted_B3HW: torch.Tensor, target_B3HW: torch.Tensor) -> None:
        """Add a batch of image pairs."""
        from torchmetrics.functional.image import peak_signal_noise_ratio
        from torchmetrics.image import PeakSignalNoiseRatio

        check_pair(predicted_B3HW, target_B3HW, "psnr")
        predicted, target = predicted_B3HW.double().cpu(), target_B3HW.double().cpu()
        self._count += len(target)
        if self.pooled:
            # torchmetrics' stateful PSNR with its default reduction is the pooled one (the sum of
            # squared errors over everything seen).
            if self._pooled is None:
                self._pooled = PeakSignalNoiseRatio(data_range=self.data_range).double()
            self._pooled.update(predicted, target)
            return
        values_B = peak_signal_noise_ratio(
            predicted, target, data_range=self.data_range, reduction="none", dim=(1, 2, 3)
        )
        # An exact match has infinite PSNR: report the cap instead of Inf.
        self._sum += float(values_B.clamp(max=self.max_db).sum())

    def compute(self) -> float:
        """The mean per-image PSNR, or the PSNR of the pooled error; capped at ``max_db``."""
        if self._count == 0:
            raise ValueError("Psnr: no images were added before compute()")
        if not self.pooled:
            return self._sum / self._count
        return min(float(self._pooled.compute()), self.max_db)

    def reset(self) -> None:
        """Forget every image seen."""
        self._sum, self._count = 0.0, 0
        self._pooled = None


# -- SSIM and MS-SSIM -------------------------------------------------------------------------------


class Ssim(PerImageMetric):
    """Structural similarity (torchmetrics, float64): the mean of the SSIM map over every pixel and channel
    (windows at the border see the image reflect-padded, torchmetrics' definition; the mean over valid
    windows only, as in Wang et al.'s code, differs most on small noisy images: 6% at 64 px, none at
    256 px), then over images."""

    higher_is_better = True

    def __init__(self, data_range: float = 1.0, window_size: int = 11, sigma: float = 1.5) -> None:
        if window_size % 2 == 0:
            raise ValueError(f"ssim window_size must be odd, got {window_size}")
        self.data_range, self.window_size, self.sigma = data_range, window_size, sigma
        super().__init__()

    def per_image(self, predicted: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """SSIM of each image pair, shape (B,), float64."""
        check_pair(predicted, target, "ssim")
        if min(predicted.shape[-2:]) < self.window_size:
            raise ValueError(f"ssim needs images of at least {self.window_size} px, got {tuple(predicted.shape[-2:])}")
        from torchmetrics.functional.image import structural_similarity_index_measure

        return structural_similarity_index_measure(
            predicted.double().cpu(),
            target.double().cpu(),
            data_range=self.data_range,
            kernel_size=self.window_size,
            sigma=self.sigma,
            reduction="none",
        )


#: Wang, Simoncelli and Bovik's five scale weights (2003), finest first.
MS_SSIM_BETAS = (0.0448, 0.2856, 0.3001, 0.2363, 0.1333)


def ms_ssim_scales(height: int, width: int, window_size: int = 11) -> int:
    """How many of the five scales torchmetrics' MS-SSIM accepts for (height, width) images: at least
    ``2 ** scales`` px and ``side // (scales - 1) ** 2 > window_size - 1`` (5 scales need 176 px or more)."""
    side = min(height, width)
    for scales in range(len(MS_SSIM_BETAS), 0, -1):
        if side >= 2**scales and side // max(1, scales - 1) ** 2 > window_size - 1:
            return scales
    return 0


class MsSsim(PerImageMetric):
    """Multi-scale SSIM (torchmetrics, float64), negative contrast terms clamped to 0 so that unlike images
    give a number in [0, 1], never NaN."""

    higher_is_better = True

    def __init__(self, data_range: float = 1.0, scales: int | None = None) -> None:
        self.data_range, self.scales = data_range, scales
        super().__init__()

    def per_image(self, predicted: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """MS-SSIM of each image pair, shape (B,), float64."""
        check_pair(predicted, target, "ms_ssim")
        possible = ms_ssim_scales(*predicted.shape[-2:])
        scales = self.scales or possible
        if scales == 0 or scales > possible:
            raise ValueError(
                f"ms_ssim with {scales or 1} scale(s) needs larger images than "
                f"{tuple(predicted.shape[-2:])} (at most {possible} scale(s) fit); set scales or use ssim"
            )
        betas = torch.tensor(MS_SSIM_BETAS[:scales], dtype=torch.float64)
        from torchmetrics.functional.image import multiscale_structural_similarity_index_measure

        return multiscale_structural_similarity_index_measure(
            predicted.double().cpu(),
            target.double().cpu(),
            data_range=self.data_range,
            betas=tuple((betas / betas.sum()).tolist()),
            normalize="relu",
            reduction="none",
        )


# -- LPIPS ----------------------------------------------------------------------------------------

#: The ImageNet trunks LPIPS compares features of (torchvision's files; never downloaded).
LPIPS_VGG_WEIGHTS = WeightsSpec(
    description="metric 'lpips' (VGG16 trunk: torchvision's ImageNet VGG16 weights)",
    filenames=("vgg16-397923af.pth",),
    env_var="VQTOUCH_LPIPS_VGG",
    config_hint="the lpips metric's weights option (e.g. --set metrics.3.weights=PATH, 3 being lpips' place in "
    "metrics) or `vqtouch evaluate pairs --lpips-weights PATH`",
    source_url="https://download.pytorch.org/models/vgg16-397923af.pth",
    sha256_prefix="397923af",
)
#: AlexNet: the same file as the tokenizer's LPIPS loss, found the same way.
LPIPS_TRUNK_WEIGHTS = {"vgg": LPIPS_VGG_WEIGHTS, "alex": ALEXNET_WEIGHTS}


def load_trunk_into_lpips(lpips_net: torch.nn.Module, state_dict: dict[str, torch.Tensor]) -> None:
    """Copy torchvision's ``features.{i}.*`` tensors into torchmetrics' LPIPS trunk, whose slices keep
    torchvision's layer indices as child names (``slice{k}.{i}``); every trunk tensor must be found."""
    trunk = {}
    for name, tensor in lpips_net.net.state_dict().items():  # "slice1.0.weight"
        _, index, kind = name.split(".")
        key = f"features.{index}.{kind}"
        if key not in state_dict or state_dict[key].shape != tensor.shape:
            raise MissingWeightsError(
                f"the LPIPS trunk file lacks {key} of shape {tuple(tensor.shape)}: it is not "
                "torchvision's ImageNet weights of this backbone"
            )
        trunk[name] = state_dict[key]
    lpips_net.net.load_state_dict(trunk, strict=True)


class Lpips(PerImageMetric):
    """LPIPS distance (lower is better) of each image pair, averaged: torchmetrics' network, v0.1 heads."""

    higher_is_better = False

    def __init__(self, lpips_net: torch.nn.Module, batch_size: int = 8) -> None:
        self.net = lpips_net.eval()
        self.batch_size = batch_size
        super().__init__()

    @torch.no_grad()
    def per_image(self, predicted: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """LPIPS of each pair (B,), computed in float32 in chunks of ``batch_size``."""
        check_pair(predicted, target, "lpips")
        if predicted.shape[1] != 3:
            raise ValueError(f"lpips needs RGB images (B, 3, H, W), got {tuple(predicted.shape)}")
        if min(predicted.shape[-2:]) < 16:
            raise ValueError(
                f"lpips needs images of at least 16 px (its trunk halves them 4 times), got "
                f"{tuple(predicted.shape[-2:])}"
            )
        self.net.to(predicted.device)
        values = [
            self.net(p.float().clamp(0, 1), t.float().clamp(0, 1), normalize=True).flatten().double().cpu()
            for p, t in zip(predicted.split(self.batch_size), target.split(self.batch_size))
        ]
        return torch.cat(values)


def build_lpips(config: LpipsConfig, context: BuildContext) -> Metric:
    """Factory for ``lpips``: torchmetrics' LPIPS holding the user's trunk weights; skipped (with the file
    to provide) when the weights file or torchvision is missing."""
    spec = LPIPS_TRUNK_WEIGHTS[config.backbone]
    try:
        path = resolve_weights(spec, config.weights)
    except MissingWeightsError as error:
        return SkippedMetric(str(error), higher_is_better=False)
    try:
        from torchmetrics.functional.image.lpips import _NoTrainLpips
    except (ImportError, ModuleNotFoundError) as error:
        return SkippedMetric(
            f"metric 'lpips' needs torchvision ({error}): pip install 'vqtouch[metrics]'", higher_is_better=False
        )
    # pnet_rand builds the trunk without torchvision's download; the file's weights are then loaded
    # into it, and the linear heads come from the file inside torchmetrics (pretrained=True).
    net = _NoTrainLpips(net=config.backbone, pnet_rand=True)
    try:
        load_trunk_into_lpips(net, torch.load(path, map_location="cpu", weights_only=True))
    except MissingWeightsError as error:  # a file, but not this trunk's: as good as missing
        return SkippedMetric(f"metric 'lpips': {path}: {error}", higher_is_better=False)
    return Lpips(net, config.batch_size)


def build_psnr(config: PsnrConfig, context: BuildContext) -> Psnr:
    """Factory for ``psnr``."""
    return Psnr(config.data_range, config.pooled, config.max_db)


def build_ssim(config: SsimConfig, context: BuildContext) -> Ssim:
    """Factory for ``ssim``."""
    return Ssim(config.data_range, config.window_size, config.sigma)


def build_ms_ssim(config: MsSsimConfig, context: BuildContext) -> MsSsim:
    """Factory for ``ms_ssim``."""
    return MsSsim(config.data_range, config.scales)

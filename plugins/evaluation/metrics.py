"""Pixel metrics with closed forms: PSNR and SSIM (pure torch, computed in float64)."""

from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F
from pydantic import Field

from vqtouch.core import BuildContext, PerImageMetric, PluginConfig, hookimpl


def _check_pair(predicted: torch.Tensor, target: torch.Tensor) -> None:
    if predicted.shape != target.shape or predicted.ndim != 4:
        raise ValueError(f"metrics need two image batches of equal shape (B, C, H, W); got "
                         f"{tuple(predicted.shape)} and {tuple(target.shape)}")
    for name, images in (("predicted", predicted), ("target", target)):
        if not torch.isfinite(images).all():
            raise ValueError(f"{name} images contain NaN or Inf")


class PsnrConfig(PluginConfig):
    """Options of the ``psnr`` metric."""

    name: Literal["psnr"] = "psnr"
    data_range: float = Field(1.0, gt=0, description="Value range of the images (1.0 for [0, 1]).")
    max_db: float = Field(100.0, gt=0, description="Cap for identical images, whose PSNR is infinite.")


class Psnr(PerImageMetric):
    """Peak signal-to-noise ratio in dB, averaged over images (each image's own MSE)."""

    higher_is_better = True

    def __init__(self, data_range: float = 1.0, max_db: float = 100.0) -> None:
        self.data_range = data_range
        self.max_db = max_db
        super().__init__()

    def per_image(self, predicted: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """PSNR of each image pair in dB, shape (B,), float64."""
        _check_pair(predicted, target)
        mse_B = (predicted.double() - target.double()).pow(2).flatten(1).mean(1)
        # An exact match has infinite PSNR: report the cap instead of Inf.
        floor = self.data_range**2 * 10 ** (-self.max_db / 10)
        return 10 * torch.log10(self.data_range**2 / mse_B.clamp_min(floor))


class SsimConfig(PluginConfig):
    """Options of the ``ssim`` metric (Wang et al. 2004, Gaussian window)."""

    name: Literal["ssim"] = "ssim"
    data_range: float = Field(1.0, gt=0, description="Value range of the images (1.0 for [0, 1]).")
    window_size: int = Field(11, ge=3, le=31, description="Side of the Gaussian window (odd).")
    sigma: float = Field(1.5, gt=0, le=10, description="Standard deviation of the Gaussian window.")


class Ssim(PerImageMetric):
    """Structural similarity, mean over pixels and channels, then over images."""

    higher_is_better = True

    def __init__(self, data_range: float = 1.0, window_size: int = 11, sigma: float = 1.5) -> None:
        if window_size % 2 == 0:
            raise ValueError(f"ssim window_size must be odd, got {window_size}")
        self.data_range = data_range
        self.window_size = window_size
        self.sigma = sigma
        super().__init__()

    def per_image(self, predicted: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """SSIM of each image pair, shape (B,), float64, over valid windows (no padding)."""
        _check_pair(predicted, target)
        if min(predicted.shape[-2:]) < self.window_size:
            raise ValueError(f"ssim needs images of at least {self.window_size} px, got {tuple(predicted.shape[-2:])}")
        x, y = predicted.double(), target.double()
        channels = x.shape[1]
        coords = torch.arange(self.window_size, dtype=torch.float64) - (self.window_size - 1) / 2
        gauss = torch.exp(-coords**2 / (2 * self.sigma**2))
        gauss = gauss / gauss.sum()
        window = (gauss[:, None] * gauss[None, :]).expand(channels, 1, -1, -1).to(x.device)

        def blur(images: torch.Tensor) -> torch.Tensor:
            return F.conv2d(images, window, groups=channels)

        c1 = (0.01 * self.data_range) ** 2
        c2 = (0.03 * self.data_range) ** 2
        mu_x, mu_y = blur(x), blur(y)
        var_x = blur(x * x) - mu_x**2
        var_y = blur(y * y) - mu_y**2
        cov = blur(x * y) - mu_x * mu_y
        ssim_map = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2))
        return ssim_map.flatten(1).mean(1)


def build_psnr(config: PsnrConfig, context: BuildContext) -> Psnr:
    """Factory for ``psnr``."""
    return Psnr(config.data_range, config.max_db)


def build_ssim(config: SsimConfig, context: BuildContext) -> Ssim:
    """Factory for ``ssim``."""
    return Ssim(config.data_range, config.window_size, config.sigma)


@hookimpl
def vqtouch_register_metrics(register):
    register("psnr", build_psnr, PsnrConfig, description="Peak signal-to-noise ratio in dB (per image, averaged).")
    register("ssim", build_ssim, SsimConfig, description="Structural similarity (Gaussian 11x11, sigma 1.5).")

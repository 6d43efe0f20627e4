"""The pairwise image metrics' plugin: the ``psnr``, ``ssim``, ``ms_ssim`` and ``lpips`` options and
registration (the metrics, in metrics.py, are imported when built)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field

from vqtouch.core import PluginConfig, hookimpl


class PsnrConfig(PluginConfig):
    """Options of the ``psnr`` metric."""

    name: Literal["psnr"] = "psnr"
    data_range: float = Field(1.0, gt=0, description="Value range of the images (1.0 for [0, 1]).")
    pooled: bool = Field(
        False,
        description="One PSNR of the squared error pooled over every pixel of every image "
        "(torchmetrics' default reduction, the published protocol's) instead of "
        "the mean of per-image PSNRs.",
    )
    max_db: float = Field(100.0, gt=0, description="Cap for identical images, whose PSNR is infinite.")


class SsimConfig(PluginConfig):
    """Options of the ``ssim`` metric (Wang et al. 2004, Gaussian window)."""

    name: Literal["ssim"] = "ssim"
    data_range: float = Field(1.0, gt=0, description="Value range of the images (1.0 for [0, 1]).")
    window_size: int = Field(11, ge=3, le=31, description="Side of the Gaussian window (odd).")
    sigma: float = Field(1.5, gt=0, le=10, description="Standard deviation of the Gaussian window.")


class MsSsimConfig(PluginConfig):
    """Options of the ``ms_ssim`` metric (multi-scale SSIM, Wang et al. 2003)."""

    name: Literal["ms_ssim"] = "ms_ssim"
    data_range: float = Field(1.0, gt=0, description="Value range of the images (1.0 for [0, 1]).")
    scales: int | None = Field(
        None,
        ge=1,
        le=5,
        description="Scales to use (the first of Wang's five weights, renormalised to sum 1). "
        "None: 5 when the images allow it (176 px or more), else the most they allow "
        "(3 at 64 px, 4 at 128 px); only compare numbers with equal scales.",
    )


class LpipsConfig(PluginConfig):
    """Options of the ``lpips`` metric (Zhang et al. 2018, v0.1 heads, via torchmetrics)."""

    name: Literal["lpips"] = "lpips"
    backbone: Literal["vgg", "alex"] = Field(
        "vgg",
        description="ImageNet trunk: vgg (the published tactile protocol's) or alex (the LPIPS authors' default).",
    )
    weights: str | None = Field(
        None,
        description="Path to torchvision's ImageNet weights of the trunk "
        "(vgg16-397923af.pth or alexnet-owt-7be5be79.pth); else "
        "VQTOUCH_LPIPS_VGG / VQTOUCH_LPIPS_BACKBONE or VQTOUCH_WEIGHTS_DIR. "
        "Without it the metric is reported as skipped.",
    )
    batch_size: int = Field(8, ge=1, le=1024, description="Image pairs per forward pass (bounds memory at 512 px).")


@hookimpl
def vqtouch_register_metrics(register: Any) -> None:
    register(
        "psnr",
        "vqtouch.plugins.evaluation.metrics:build_psnr",
        PsnrConfig,
        description="Peak signal-to-noise ratio in dB (torchmetrics; per image, averaged).",
    )
    register(
        "ssim",
        "vqtouch.plugins.evaluation.metrics:build_ssim",
        SsimConfig,
        description="Structural similarity (torchmetrics; Gaussian 11x11, sigma 1.5).",
    )
    register(
        "ms_ssim",
        "vqtouch.plugins.evaluation.metrics:build_ms_ssim",
        MsSsimConfig,
        description="Multi-scale structural similarity (torchmetrics; 5 scales from 176 px, fewer below).",
    )
    register(
        "lpips",
        "vqtouch.plugins.evaluation.metrics:build_lpips",
        LpipsConfig,
        description="LPIPS v0.1 (torchmetrics) with a VGG16 or AlexNet trunk "
        "from a user-supplied file; skipped without it.",
    )

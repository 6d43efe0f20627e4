"""The ``fd_effnetlite0`` metric's plugin: its options and registration (the metric, in fd_metric.py, is
imported when built)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field

from vqtouch.core import PluginConfig, hookimpl


class FdEffNetLite0Config(PluginConfig):
    """Options of the ``fd_effnetlite0`` metric."""

    name: Literal["fd_effnetlite0"] = "fd_effnetlite0"
    image_size: int = Field(
        224,
        ge=32,
        le=1024,
        description="Side images are resized to before EfficientNet-Lite0 (224 = its training "
        "size; only compare numbers computed with the same value).",
    )
    batch_size: int = Field(32, ge=1, le=4096, description="Images per forward pass of the feature network.")


@hookimpl
def vqtouch_register_metrics(register: Any) -> None:
    register(
        "fd_effnetlite0",
        "vqtouch.plugins.evaluation.fd_metric:build_fd_effnetlite0",
        FdEffNetLite0Config,
        description="Fréchet distance on EfficientNet-Lite0 ImageNet features (not FID; for ordering, "
        "rank-deficient below 1280 samples).",
    )

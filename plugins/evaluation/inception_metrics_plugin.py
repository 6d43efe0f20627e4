"""The ``fid``, ``kid`` and ``kid_effnetlite0`` metrics' plugin: their options and registration (the metrics,
in inception_metrics.py, are imported when built)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field

from vqtouch.core import PluginConfig, hookimpl


class FidConfig(PluginConfig):
    """Options of the ``fid`` metric (standard FID: Inception-v3 2048-d features, torchmetrics)."""

    name: Literal["fid"] = "fid"
    weights: str | None = Field(
        None,
        description="Path to weights-inception-2015-12-05-6726825d.pth (torch-fidelity's "
        "Inception-v3); else VQTOUCH_FID_INCEPTION or VQTOUCH_WEIGHTS_DIR. "
        "Without it the metric is reported as skipped.",
    )


class KidConfig(PluginConfig):
    """Options of the ``kid`` metric (standard KID on Inception-v3 2048-d features, torchmetrics)."""

    name: Literal["kid"] = "kid"
    weights: str | None = Field(
        None,
        description="Path to weights-inception-2015-12-05-6726825d.pth; else "
        "VQTOUCH_FID_INCEPTION or VQTOUCH_WEIGHTS_DIR. Without it the "
        "metric is reported as skipped.",
    )
    subsets: int = Field(100, ge=1, le=10000, description="Random subsets KID is averaged over.")
    subset_size: int = Field(1000, ge=2, description="Images per subset (capped at the smaller set's size).")
    seed: int = Field(0, description="Seed of the subset draws.")


class KidEffNetLite0Config(PluginConfig):
    """Options of the ``kid_effnetlite0`` metric (KID on fd_effnetlite0's EfficientNet-Lite0 features)."""

    name: Literal["kid_effnetlite0"] = "kid_effnetlite0"
    image_size: int = Field(
        224,
        ge=32,
        le=1024,
        description="Side images are resized to before EfficientNet-Lite0 "
        "(as fd_effnetlite0's; compare equal values only).",
    )
    batch_size: int = Field(32, ge=1, le=4096, description="Images per forward pass of the feature network.")
    subsets: int = Field(100, ge=1, le=10000, description="Random subsets KID is averaged over.")
    subset_size: int = Field(1000, ge=2, description="Images per subset (capped at the smaller set's size).")
    seed: int = Field(0, description="Seed of the subset draws.")


@hookimpl
def vqtouch_register_metrics(register: Any) -> None:
    register(
        "fid",
        "vqtouch.plugins.evaluation.inception_metrics:build_fid",
        FidConfig,
        description="Standard FID (torchmetrics, Inception-v3 from a user-supplied file); skipped without it.",
    )
    register(
        "kid",
        "vqtouch.plugins.evaluation.inception_metrics:build_kid",
        KidConfig,
        description="Standard KID (torchmetrics, Inception-v3 from a user-supplied file); skipped without it.",
    )
    register(
        "kid_effnetlite0",
        "vqtouch.plugins.evaluation.inception_metrics:build_kid_effnetlite0",
        KidEffNetLite0Config,
        description="KID on fd_effnetlite0's EfficientNet-Lite0 features (offline; not the standard KID).",
    )

"""The ``procedural`` dataset's plugin: its options and registration (the dataset, in procedural.py, is imported
when built)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator

from vqtouch.core import PluginConfig, hookimpl
from vqtouch.core.image_size import ImageSize, ImageSizeOption, image_hw, size_text

#: The scene library's object classes, in order: vqtouch.sensors.objects.CLASS_NAMES, spelled out here
#: because that module imports torch (a test checks that the two agree).
CLASS_NAMES: tuple[str, ...] = (
    "sphere",
    "cylinder",
    "edge",
    "cube_corner",
    "ridges",
    "grating",
    "knurl",
    "weave",
    "dots",
    "digits",
    "rock",
    "cloth_folds",
)


class ProceduralDataConfig(PluginConfig):
    """Options of the ``procedural`` dataset (the embedded default data)."""

    name: Literal["procedural"] = "procedural"
    num_samples: int = Field(1000, ge=1, le=10_000_000, description="Number of samples in the dataset.")
    image_size: ImageSizeOption | None = Field(
        None,
        description="Size of the tactile and visual images, 16 to 1024 px a side: S for S x S, or [height, "
        "width] (the sensor's imaged area is then resampled to that shape: set a sensor view of "
        "the same aspect, e.g. GelSight's view=full for [240, 320]); null uses the "
        "experiment's data.image_size.",
    )
    seed: int = Field(0, ge=0, le=2**31 - 1, description="Seed; sample i depends only on (seed, i).")
    classes: list[str] = Field(
        default_factory=list, description=f"Object classes to draw (empty: all). Known: {', '.join(CLASS_NAMES)}."
    )
    depth_mm: tuple[float, float] = Field((0.2, 1.0), description="Range of press depths in mm.")
    cache: bool = Field(True, description="Keep rendered samples in memory (as 8-bit images).")

    @field_validator("image_size")
    @classmethod
    def _renderable_size(cls, size: ImageSize | None) -> ImageSize | None:
        if size is not None and not all(16 <= side <= 1024 for side in image_hw(size)):
            raise ValueError(f"image_size {size_text(size)}: each side must be 16 to 1024 px")
        return size

    @field_validator("classes")
    @classmethod
    def _known_classes(cls, classes: list[str]) -> list[str]:
        unknown = [name for name in classes if name not in CLASS_NAMES]
        if unknown:
            raise ValueError(f"unknown object classes {unknown}; known: {', '.join(CLASS_NAMES)}")
        if len(set(classes)) != len(classes):
            raise ValueError("object classes are listed twice")
        return classes

    @field_validator("depth_mm")
    @classmethod
    def _depth_range(cls, depth: tuple[float, float]) -> tuple[float, float]:
        if not 0 < depth[0] <= depth[1] <= 5:
            raise ValueError(f"depth_mm must satisfy 0 < low <= high <= 5 mm, got {depth}")
        return depth


@hookimpl
def vqtouch_register_datasets(register):
    register(
        "procedural",
        "vqtouch.plugins.data.procedural:build_procedural",
        ProceduralDataConfig,
        inputs=("sensor",),
        optional_inputs=("paired_sensor",),
        demo={"num_samples": 240},
        description="Embedded procedural scenes: 12 object classes x any sensor family (tactile, visual, "
        "label, text; tactile_source with a paired sensor).",
    )

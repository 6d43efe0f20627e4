"""The tactile conditioner's plugin: its options and registration (the model, in tactile.py, is imported when built)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from vqtouch.core import hookimpl

from .image_cnn_options import ImageCnnOptions


class TactileConditionerConfig(ImageCnnOptions):
    """Options of the ``tactile`` conditioner."""

    name: Literal["tactile"] = "tactile"
    reads: Literal["tactile_source", "tactile"] = Field(
        "tactile_source",
        description="Sample entry encoded: 'tactile_source' (the paired sensor's image of the same "
        "contact; set the experiment's paired_sensor) or 'tactile' (the target image "
        "itself: a sanity check, not a task).",
    )


@hookimpl
def vqtouch_register_conditioners(register):
    register(
        "tactile",
        "vqtouch.conditioners.tactile:build_tactile_conditioner",
        TactileConditionerConfig,
        description="Trainable CNN tokens from another sensor's tactile image of the contact (touch-to-touch).",
    )

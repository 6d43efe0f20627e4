"""The visual_cnn conditioner's plugin: its options and registration
(the model, in visual_cnn.py, is imported when built)."""

from __future__ import annotations

from typing import Literal

from vqtouch.core import hookimpl

from .image_cnn_options import ImageCnnOptions


class VisualCnnConditionerConfig(ImageCnnOptions):
    """Options of the ``visual_cnn`` conditioner."""

    name: Literal["visual_cnn"] = "visual_cnn"


@hookimpl
def vqtouch_register_conditioners(register):
    register(
        "visual_cnn",
        "vqtouch.conditioners.visual_cnn:build_visual_cnn_conditioner",
        VisualCnnConditionerConfig,
        description="CNN trained from scratch: tokens from a visual RGB image (vision-to-touch, "
        "no pretrained weights).",
    )

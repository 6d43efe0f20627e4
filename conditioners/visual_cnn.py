"""Visual CNN conditioner: a small CNN trained from scratch turning a visual image into a grid of tokens.

The same network as the ``tactile`` conditioner
(:class:`vqtouch.conditioners.image_cnn.ImageCnnConditioner`), reading samples' ``"visual"``
RGB image instead.  No pretrained weights: the pretrained alternative is the ``visual``
conditioner (frozen ImageNet EfficientNet-Lite0).
"""

from __future__ import annotations

from typing import Literal

from vqtouch.core import BuildContext, hookimpl

from .image_cnn import ImageCnnConditioner, ImageCnnOptions


class VisualCnnConditionerConfig(ImageCnnOptions):
    """Options of the ``visual_cnn`` conditioner."""

    name: Literal["visual_cnn"] = "visual_cnn"


def build_visual_cnn_conditioner(config: VisualCnnConditionerConfig, context: BuildContext) -> ImageCnnConditioner:
    """Factory for the ``visual_cnn`` conditioner: visual images are always RGB (3 channels)."""
    return ImageCnnConditioner("visual", context.cond_dim, config.width, config.depth, config.token_grid, channels=3)


@hookimpl
def vqtouch_register_conditioners(register):
    register("visual_cnn", build_visual_cnn_conditioner, VisualCnnConditionerConfig,
             description="CNN trained from scratch: tokens from a visual RGB image (vision-to-touch, "
                         "no pretrained weights).")

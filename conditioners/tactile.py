"""Tactile conditioner: a small trainable CNN turning a tactile image into a grid of tokens.

The network is :class:`vqtouch.conditioners.image_cnn.ImageCnnConditioner`, shared with the
``visual_cnn`` conditioner; this module registers it reading samples' ``"tactile"`` image.
"""

from __future__ import annotations

from typing import Literal

from vqtouch.core import BuildContext, hookimpl

from .image_cnn import ImageCnnConditioner, ImageCnnOptions

#: The tactile conditioner's class (kept under its historical name for imports).
TactileConditioner = ImageCnnConditioner


class TactileConditionerConfig(ImageCnnOptions):
    """Options of the ``tactile`` conditioner."""

    name: Literal["tactile"] = "tactile"


def build_tactile_conditioner(config: TactileConditionerConfig, context: BuildContext) -> ImageCnnConditioner:
    """Factory for the ``tactile`` conditioner: the tactile image has the context's channel count."""
    return ImageCnnConditioner("tactile", context.cond_dim, config.width, config.depth, config.token_grid,
                               context.channels)


@hookimpl
def vqtouch_register_conditioners(register):
    register("tactile", build_tactile_conditioner, TactileConditionerConfig,
             description="Trainable CNN tokens from a tactile image (touch-to-touch).")

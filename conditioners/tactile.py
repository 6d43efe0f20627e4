"""Tactile conditioner: a small trainable CNN turning a tactile image into a grid of tokens.

The network is :class:`vqtouch.conditioners.image_cnn.ImageCnnConditioner`, shared with the
``visual_cnn`` conditioner.  By default it reads a sample's ``"tactile_source"``: the same contact
imaged by the experiment's ``paired_sensor`` (touch-to-touch across sensors, e.g. GelSight ->
DIGIT, with exact ground truth).  ``reads="tactile"`` conditions on the very image the generator
learns to produce (an autoencoding sanity check, which the generator stage warns about).
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from vqtouch.core import BuildContext, hookimpl

from .image_cnn import ImageCnnConditioner, ImageCnnOptions, grid_stage_for

#: The tactile conditioner's class (kept under its historical name for imports).
TactileConditioner = ImageCnnConditioner


class TactileConditionerConfig(ImageCnnOptions):
    """Options of the ``tactile`` conditioner."""

    name: Literal["tactile"] = "tactile"
    reads: Literal["tactile_source", "tactile"] = Field(
        "tactile_source",
        description="Sample entry encoded: 'tactile_source' (the paired sensor's image of the same "
        "contact; set the experiment's paired_sensor) or 'tactile' (the target image "
        "itself: a sanity check, not a task).",
    )


def build_tactile_conditioner(config: TactileConditionerConfig, context: BuildContext) -> ImageCnnConditioner:
    """Factory for the ``tactile`` conditioner: the tactile image has the context's channel count."""
    grid_stage = grid_stage_for(context.image_size, context.code_grid, config.depth) if config.spatial else None
    return ImageCnnConditioner(
        config.reads,
        context.cond_dim,
        config.width,
        config.depth,
        config.token_grid,
        context.channels,
        grid_stage=grid_stage,
        grid_context=config.grid_context if grid_stage is not None else (),
        grid_context_width=config.grid_context_width if grid_stage is not None else None,
    )


@hookimpl
def vqtouch_register_conditioners(register):
    register(
        "tactile",
        build_tactile_conditioner,
        TactileConditionerConfig,
        description="Trainable CNN tokens from another sensor's tactile image of the contact (touch-to-touch).",
    )

"""Tactile conditioner: a small trainable CNN turning a tactile image into a grid of tokens.

The network is :class:`vqtouch.conditioners.image_cnn.ImageCnnConditioner`, shared with the
``visual_cnn`` conditioner.  By default it reads a sample's ``"tactile_source"``: the same contact
imaged by the experiment's ``paired_sensor`` (touch-to-touch across sensors, e.g. GelSight ->
DIGIT, with exact ground truth).  ``reads="tactile"`` conditions on the very image the generator
learns to produce (an autoencoding sanity check, which the generator stage warns about).
"""

from __future__ import annotations

from vqtouch.core import BuildContext

from .image_cnn import ImageCnnConditioner, grid_stage_for
from .tactile_plugin import TactileConditionerConfig

#: The tactile conditioner's class (kept under its historical name for imports).
TactileConditioner = ImageCnnConditioner


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

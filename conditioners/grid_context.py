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
from pydantic import Field
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


def check_dilations(dilations: Sequence[int]) -> list[int]:
    """The dilations as a list; ValueError naming the bad one."""
    for dilation in dilations:
        if not 1 <= int(dilation) <= MAX_DILATION:
            raise ValueError(f"grid_context dilations must be 1..{MAX_DILATION}; got {dilation}")
    return [int(d) for d in dilations]


class GridContext(nn.Module):
    """``len(dilations)`` residual blocks SiLU -> Conv3x3(dilation) over (B, D, h, w).

    No normalisation inside: a norm's statistics would couple every cell to every other, and the
    generator L2-normalises each cell of the grid it reads anyway.  A cell sees exactly
    ``sum(dilations)`` cells to each side."""

    def __init__(self, channels: int, dilations: Sequence[int]) -> None:
        super().__init__()
        self.dilations = check_dilations(dilations)
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

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

Cost: a 3 x 3 convolution at the grid's full width (the generator's ``cond_dim``) is 9 cond_dim**2
multiply-adds per cell; on a 16 x 16 grid four of them cost about as much per training step as the
generator itself on a 2-core CPU.  ``width`` runs the blocks on a narrower map between two 1 x 1
convolutions (the second zero-initialised, so the stack still starts as the identity), at
(width / cond_dim)**2 of that cost.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from pydantic import TypeAdapter
from torch import nn

from .grid_context_options import (  # noqa: F401 - re-exported: their home before
    GRID_CONTEXT_FIELD,
    GRID_CONTEXT_WIDTH_FIELD,
    MAX_DILATION,
    GridDilations,
    check_context_width,
)


def grid_context_for(
    channels: int, dilations: Sequence[int], has_grid: bool, width: int | None = None
) -> GridContext | None:
    """The stack a conditioner with a condition grid of ``channels`` builds (its blocks at ``width``
    channels, None: ``channels``): None for no dilations; ValueError when there are dilations but no
    grid to apply them to, or a width without dilations."""
    check_context_width(dilations, width)
    if not dilations:
        return None
    if not has_grid:
        raise ValueError(
            "grid_context needs a condition grid: enable the conditioner's grid, or leave grid_context empty"
        )
    return GridContext(channels, dilations, width)


class GridContext(nn.Module):
    """``len(dilations)`` residual blocks SiLU -> Conv3x3(dilation) over (B, D, h, w).

    No normalisation inside: a norm's statistics would couple every cell to every other, and the
    generator L2-normalises each cell of the grid it reads anyway.  A cell sees exactly the offsets
    that are sums of one of -d, 0, +d per block (every offset up to ``sum(dilations)`` for 1, 2, 4, ...).

    With ``width`` (other than ``channels``) the blocks run on a ``width``-channel map: 1x1 down, the
    blocks, 1x1 up, added to the input.  The up-projection starts at zero instead of each block's last
    convolution, so the stack starts as the identity and the blocks start trained-from-scratch."""

    def __init__(self, channels: int, dilations: Sequence[int], width: int | None = None) -> None:
        super().__init__()
        # The config's own check, for stacks built directly in Python.
        self.dilations = TypeAdapter(GridDilations).validate_python(list(dilations))
        narrow = width is not None and width != channels
        inner = width if narrow else channels
        self.narrow = nn.Conv2d(channels, inner, 1) if narrow else None
        self.widen = nn.Conv2d(inner, channels, 1) if narrow else None
        self.blocks = nn.ModuleList()
        for dilation in self.dilations:
            conv = nn.Conv2d(inner, inner, 3, padding=dilation, dilation=dilation)
            if not narrow:
                nn.init.zeros_(conv.weight)
                nn.init.zeros_(conv.bias)
            self.blocks.append(nn.Sequential(nn.SiLU(), conv))
        if self.widen is not None:
            nn.init.zeros_(self.widen.weight)
            nn.init.zeros_(self.widen.bias)

    def forward(self, grid_BDhw: torch.Tensor) -> torch.Tensor:
        inner_BWhw = grid_BDhw if self.narrow is None else self.narrow(grid_BDhw)
        for block in self.blocks:
            inner_BWhw = inner_BWhw + block(inner_BWhw)
        return inner_BWhw if self.widen is None else grid_BDhw + self.widen(inner_BWhw)

    def extra_repr(self) -> str:
        width = "" if self.narrow is None else f", width={self.narrow.out_channels}"
        return f"dilations={self.dilations}{width}"

"""The one small trainable image CNN behind the ``tactile`` and ``visual_cnn`` conditioners.

Both plugins encode an RGB image of a sample into a grid of tokens with the same network,
trained from scratch with the generator; they differ only in which entry of a sample they
read (``"tactile_source"`` or ``"tactile"``, or ``"visual"``).  So the network lives here once, parametrised by the
sample key, and each plugin module registers it under its own name with its own config
class (same options: width, depth, token_grid).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from vqtouch.core import Conditioner, load_missing_as_zeros
from vqtouch.core.image_size import image_hw

from .grid_context import grid_context_for
from .image_cnn_options import ImageCnnOptions  # noqa: F401 - re-exported: its home before

#: The sample entries that hold an image this network can read (see ``TactileDataset``).
IMAGE_SAMPLE_KEYS = ("tactile_source", "tactile", "visual")


class ImageCnnConditioner(Conditioner):
    """Encodes the images (B, C, H, W) in [0, 1] of one sample entry into token_grid**2 condition tokens.

    ``depth`` stride-2 conv + GroupNorm + SiLU stages, adaptive average pooling to a
    ``token_grid`` x ``token_grid`` grid, a linear projection of each cell to ``cond_dim`` and a
    learned position embedding per cell.  ``sample_key`` (one of ``IMAGE_SAMPLE_KEYS``) is set
    per instance: one class serves every plugin that registers it.

    With ``grid_stage`` (the trunk stage whose map is nearest the generator's code grid, see
    :func:`grid_stage_for`), :meth:`encode_with_grid` also returns that stage's map, projected
    to ``cond_dim`` by a 1x1 convolution: the condition at each place of the target image.
    """

    def __init__(
        self,
        sample_key: str,
        cond_dim: int,
        width: int,
        depth: int,
        token_grid: int,
        channels: int = 3,
        grid_stage: int | None = None,
        grid_context: Sequence[int] = (),
        grid_context_width: int | None = None,
    ) -> None:
        """``sample_key``: the sample entry read; ``channels``: its image channels (3 for RGB);
        ``grid_stage``: the trunk stage (0-based) whose map is the condition grid, None for none;
        ``grid_context``: dilations of a :class:`GridContext` over that map, its convolutions at
        ``grid_context_width`` channels (None: ``cond_dim``)."""
        if sample_key not in IMAGE_SAMPLE_KEYS:
            raise ValueError(f"the CNN image conditioner reads one of {IMAGE_SAMPLE_KEYS}, got {sample_key!r}")
        super().__init__(cond_dim, token_grid * token_grid)
        # An instance attribute shadows the class-level Conditioner.sample_key: every reader of it
        # (condition_of, parse_condition, the pipeline) looks it up on the instance.
        self.sample_key = sample_key
        self.channels = channels
        self.token_grid = token_grid
        layers: list[nn.Module] = []
        in_ch = channels
        for _ in range(depth):
            layers += [nn.Conv2d(in_ch, width, 3, stride=2, padding=1), nn.GroupNorm(min(8, width), width), nn.SiLU()]
            in_ch = width
        self.trunk = nn.Sequential(*layers)
        self.project = nn.Linear(width, cond_dim)
        self.position_ND = nn.Parameter(torch.randn(token_grid * token_grid, cond_dim) * 0.02)
        if grid_stage is not None and not 0 <= grid_stage < depth:
            raise ValueError(f"grid_stage must be one of the trunk's stages 0..{depth - 1}; got {grid_stage}")
        self.grid_stage = grid_stage
        self.grid_project = nn.Conv2d(width, cond_dim, 1) if grid_stage is not None else None
        if self.grid_project is not None:
            # Checkpoints from before the grid existed load it as zeros (the generator then sees no grid).
            load_missing_as_zeros(self, "grid_project")
        self.grid_context = grid_context_for(cond_dim, grid_context, grid_stage is not None, grid_context_width)

    def encode(self, condition: torch.Tensor) -> torch.Tensor:
        """Images (B, C, H, W), values in [0, 1], to tokens (B, token_grid**2, cond_dim)."""
        return self.encode_with_grid(condition)[0]

    def encode_with_grid(self, condition: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Images (B, C, H, W) in [0, 1] to tokens (B, token_grid**2, cond_dim) and, with a
        ``grid_stage``, that stage's projected map (B, cond_dim, h, w)."""
        images_BCHW = condition
        if images_BCHW.ndim != 4 or images_BCHW.shape[1] != self.channels:
            raise ValueError(
                f"{self.sample_key} conditioner expects images (B, {self.channels}, H, W), "
                f"got {tuple(images_BCHW.shape)}"
            )
        features_BWhw = images_BCHW.to(self.project.weight.dtype) * 2 - 1
        grid_BDhw = None
        layers_per_stage = 3
        for index, layer in enumerate(self.trunk):
            features_BWhw = layer(features_BWhw)
            if self.grid_stage is not None and index == layers_per_stage * (self.grid_stage + 1) - 1:
                grid_BDhw = self.grid_project(features_BWhw)
                if self.grid_context is not None:
                    grid_BDhw = self.grid_context(grid_BDhw)
        pooled_BWgg = F.adaptive_avg_pool2d(features_BWhw, self.token_grid)
        cells_BNW = pooled_BWgg.flatten(2).transpose(1, 2)
        return self.project(cells_BNW) + self.position_ND, grid_BDhw

    def extra_repr(self) -> str:
        return (
            f"sample_key={self.sample_key!r}, channels={self.channels}, token_grid={self.token_grid}, "
            f"grid_stage={self.grid_stage}"
        )


def grid_stage_for(image_size: Any, code_grid: Any, depth: int) -> int | None:
    """The trunk stage (0-based; stage k halves the image k + 1 times) whose map is the smallest
    that still covers the code grid, capped at the last stage; None when the code grid is unknown
    (``code_grid`` 0: a conditioner built outside a generator)."""
    image_h = image_hw(image_size)[0]
    grid_h = image_hw(code_grid)[0] if code_grid else 0
    if grid_h < 1:
        return None
    stage = 0
    while stage + 1 < depth and image_h // 2 ** (stage + 2) >= grid_h:
        stage += 1
    return stage

"""The one small trainable image CNN behind the ``tactile`` and ``visual_cnn`` conditioners.

Both plugins encode an RGB image of a sample into a grid of tokens with the same network,
trained from scratch with the generator; they differ only in which entry of a sample they
read (``"tactile_source"`` or ``"tactile"``, or ``"visual"``).  So the network lives here once, parametrised by the
sample key, and each plugin module registers it under its own name with its own config
class (same options: width, depth, token_grid).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from pydantic import Field
from torch import nn

from vqtouch.core import Conditioner, PluginConfig

#: The sample entries that hold an image this network can read (see ``TactileDataset``).
IMAGE_SAMPLE_KEYS = ("tactile_source", "tactile", "visual")


class ImageCnnOptions(PluginConfig):
    """Options shared by the CNN image conditioners; subclasses narrow ``name`` to their plugin name."""

    width: int = Field(64, ge=8, le=1024, description="Channels of the convolutional trunk.")
    depth: int = Field(3, ge=1, le=6, description="Stride-2 convolution stages before pooling.")
    token_grid: int = Field(4, ge=1, le=32, description="Tokens form a token_grid x token_grid grid.")


class ImageCnnConditioner(Conditioner):
    """Encodes the images (B, C, H, W) in [0, 1] of one sample entry into token_grid**2 condition tokens.

    ``depth`` stride-2 conv + GroupNorm + SiLU stages, adaptive average pooling to a
    ``token_grid`` x ``token_grid`` grid, a linear projection of each cell to ``cond_dim`` and a
    learned position embedding per cell.  ``sample_key`` (one of ``IMAGE_SAMPLE_KEYS``) is set
    per instance: one class serves every plugin that registers it.
    """

    def __init__(self, sample_key: str, cond_dim: int, width: int, depth: int, token_grid: int,
                 channels: int = 3) -> None:
        """``sample_key``: the sample entry read; ``channels``: its image channels (3 for RGB)."""
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

    def encode(self, condition: torch.Tensor) -> torch.Tensor:
        """Images (B, C, H, W), values in [0, 1], to tokens (B, token_grid**2, cond_dim)."""
        images_BCHW = condition
        if images_BCHW.ndim != 4 or images_BCHW.shape[1] != self.channels:
            raise ValueError(f"{self.sample_key} conditioner expects images (B, {self.channels}, H, W), "
                             f"got {tuple(images_BCHW.shape)}")
        features_BWhw = self.trunk(images_BCHW.to(self.project.weight.dtype) * 2 - 1)
        pooled_BWgg = F.adaptive_avg_pool2d(features_BWhw, self.token_grid)
        cells_BNW = pooled_BWgg.flatten(2).transpose(1, 2)
        return self.project(cells_BNW) + self.position_ND

    def extra_repr(self) -> str:
        return f"sample_key={self.sample_key!r}, channels={self.channels}, token_grid={self.token_grid}"

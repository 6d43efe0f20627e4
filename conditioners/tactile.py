"""Tactile conditioner: a small trainable CNN turning a tactile image into a grid of tokens."""

from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F
from pydantic import Field
from torch import nn

from vqtouch.core import BuildContext, Conditioner, PluginConfig, hookimpl


class TactileConditionerConfig(PluginConfig):
    """Options of the ``tactile`` conditioner."""

    name: Literal["tactile"] = "tactile"
    width: int = Field(64, ge=8, le=1024, description="Channels of the convolutional trunk.")
    depth: int = Field(3, ge=1, le=6, description="Stride-2 convolution stages before pooling.")
    token_grid: int = Field(4, ge=1, le=32, description="Tokens form a token_grid x token_grid grid.")


class TactileConditioner(Conditioner):
    """Encodes tactile images (B, 3, H, W) in [0, 1] into token_grid**2 condition tokens."""

    sample_key = "tactile"

    def __init__(self, cond_dim: int, width: int, depth: int, token_grid: int, channels: int = 3) -> None:
        super().__init__(cond_dim, token_grid * token_grid)
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
        """Tactile images (B, C, H, W), values in [0, 1], to tokens (B, token_grid**2, cond_dim)."""
        images = condition
        if images.ndim != 4 or images.shape[1] != self.channels:
            raise ValueError(f"tactile conditioner expects images (B, {self.channels}, H, W), got {tuple(images.shape)}")
        features = self.trunk(images.to(self.project.weight.dtype) * 2 - 1)
        pooled_BChw = F.adaptive_avg_pool2d(features, self.token_grid)
        tokens = pooled_BChw.flatten(2).transpose(1, 2)
        return self.project(tokens) + self.position_ND


def build_tactile_conditioner(config: TactileConditionerConfig, context: BuildContext) -> TactileConditioner:
    """Factory for the ``tactile`` conditioner."""
    return TactileConditioner(context.cond_dim, config.width, config.depth, config.token_grid, context.channels)


@hookimpl
def vqtouch_register_conditioners(register):
    register("tactile", build_tactile_conditioner, TactileConditionerConfig,
             description="Trainable CNN tokens from a tactile image (touch-to-touch).")

"""VQGAN building blocks (Esser et al. 2021): ResNet blocks, spatial attention, resampling.

GroupNorm everywhere (``norm_groups`` must divide the channel counts), swish activations,
1x1 shortcuts when channels change.  Under bf16 autocast the convolutions run in bf16 while the
norms and the residual stream stay float32 (as the generator's LayerNorms and residuals do), so
the stream's small updates are not rounded away; in float32 every block computes what it did.  A
block's second 3x3 convolution can be swapped for any layer with the same signature (DM-VQGAN puts
a deformable convolution there).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import nn

ConvFactory = Callable[[int, int], nn.Module]


def plain_conv3x3(in_channels: int, out_channels: int) -> nn.Module:
    """The default 3x3 convolution (padding 1) of a ResNet block."""
    return nn.Conv2d(in_channels, out_channels, 3, padding=1)


class Float32GroupNorm(nn.GroupNorm):
    """GroupNorm whose statistics and output are float32 whatever the autocast (bf16 statistics over a
    group's many values lose digits); in float32 it is ``nn.GroupNorm`` exactly."""

    def forward(self, x_BCHW: torch.Tensor) -> torch.Tensor:
        with torch.autocast(x_BCHW.device.type, enabled=False):
            return F.group_norm(x_BCHW.float(), self.num_groups, self.weight, self.bias, self.eps)


def group_norm(channels: int, groups: int) -> nn.GroupNorm:
    """GroupNorm with taming's eps, computed in float32; ``groups`` must divide ``channels``."""
    if channels % groups:
        raise ValueError(f"GroupNorm needs channels divisible by norm_groups: {channels} % {groups} != 0")
    return Float32GroupNorm(groups, channels, eps=1e-6, affine=True)


class ResnetBlock(nn.Module):
    """h = conv(swish(GN(x))); h = conv2(dropout(swish(GN(h)))); out = shortcut(x) + h."""

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        norm_groups: int,
        dropout: float = 0.0,
        second_conv: ConvFactory = plain_conv3x3,
    ) -> None:
        super().__init__()
        self.norm1 = group_norm(in_channels, norm_groups)
        self.conv1 = nn.Conv2d(in_channels, out_channels, 3, padding=1)
        self.norm2 = group_norm(out_channels, norm_groups)
        self.dropout = nn.Dropout(dropout)
        self.conv2 = second_conv(out_channels, out_channels)
        self.shortcut = nn.Conv2d(in_channels, out_channels, 1) if in_channels != out_channels else nn.Identity()

    def forward(self, x_BCHW: torch.Tensor) -> torch.Tensor:
        h = self.conv1(F.silu(self.norm1(x_BCHW)))
        h = self.conv2(self.dropout(F.silu(self.norm2(h))))
        return self.shortcut(x_BCHW).float() + h.float()  # the residual stream stays float32 under autocast


class AttentionBlock(nn.Module):
    """Single-head spatial self-attention with a residual; O((HW)^2) memory, so low resolutions only."""

    def __init__(self, channels: int, norm_groups: int) -> None:
        super().__init__()
        self.norm = group_norm(channels, norm_groups)
        self.qkv = nn.Conv2d(channels, 3 * channels, 1)
        self.proj = nn.Conv2d(channels, channels, 1)

    def forward(self, x_BCHW: torch.Tensor) -> torch.Tensor:
        batch, channels, height, width = x_BCHW.shape
        q, k, v = self.qkv(self.norm(x_BCHW)).reshape(batch, 3, channels, height * width).unbind(1)
        # scaled_dot_product_attention wants (B, heads, L, C); one head.
        out_BLC = F.scaled_dot_product_attention(
            q.transpose(1, 2)[:, None], k.transpose(1, 2)[:, None], v.transpose(1, 2)[:, None]
        )[:, 0]
        return x_BCHW.float() + self.proj(out_BLC.transpose(1, 2).reshape(batch, channels, height, width)).float()


class Downsample(nn.Module):
    """Asymmetric pad (0, 1, 0, 1) then a stride-2 3x3 convolution, as in taming."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(channels, channels, 3, stride=2)

    def forward(self, x_BCHW: torch.Tensor) -> torch.Tensor:
        return self.conv(F.pad(x_BCHW, (0, 1, 0, 1)))


class Upsample(nn.Module):
    """Nearest-neighbour x2 then a 3x3 convolution."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(channels, channels, 3, padding=1)

    def forward(self, x_BCHW: torch.Tensor) -> torch.Tensor:
        return self.conv(F.interpolate(x_BCHW, scale_factor=2.0, mode="nearest"))


class MultiScaleFusion(nn.Module):
    """DM-VQGAN's multi-scale dilated fusion: x + conv3x3(concat_d swish(GN(dilated_conv_d(x)))).

    Each branch sees a different receptive field (dilation 1, 2, 4 by default); the fusing
    convolution is zero-initialised so the module starts as the identity and cannot disturb
    an otherwise working network early in training.
    """

    def __init__(self, channels: int, norm_groups: int, dilations: tuple[int, ...] = (1, 2, 4)) -> None:
        super().__init__()
        self.branches = nn.ModuleList(
            nn.Sequential(
                nn.Conv2d(channels, channels, 3, padding=d, dilation=d), group_norm(channels, norm_groups), nn.SiLU()
            )
            for d in dilations
        )
        self.fuse = nn.Conv2d(channels * len(dilations), channels, 3, padding=1)
        nn.init.zeros_(self.fuse.weight)
        nn.init.zeros_(self.fuse.bias)

    def forward(self, x_BCHW: torch.Tensor) -> torch.Tensor:
        return x_BCHW.float() + self.fuse(torch.cat([branch(x_BCHW) for branch in self.branches], dim=1)).float()

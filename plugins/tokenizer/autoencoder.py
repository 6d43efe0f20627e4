"""The VQGAN autoencoder and DM-VQGAN, registered as the ``vqgan`` and ``dm_vqgan`` encoders.

One network serves both: DM-VQGAN is VQGAN plus deformable convolutions in the ResNet
blocks of the lowest-resolution feature levels (encoder and decoder; ``deformable_levels``
counts them from the latent end, so the same layers are deformable at every image size) and
the multi-scale dilated fusion module at the latent end of each half.  The DM options live
only in the ``dm_vqgan`` config, so ``--set tokenizer.encoder.name=vqgan`` is the paper's
ablation, and ``deformable_levels=0`` or ``fusion=false`` ablate the two DM parts separately.

Downsampling factor f = 2 ** (len(channel_multipliers) - 1); images in [-1, 1].
"""

from __future__ import annotations

from functools import partial

import torch
import torch.nn.functional as F
from torch import nn

from vqtouch.core import Autoencoder, BuildContext, ConfigError
from vqtouch.core.image_size import ImageSize, image_hw, size_text

from .blocks import (
    AttentionBlock,
    ConvFactory,
    Downsample,
    MultiScaleFusion,
    ResnetBlock,
    Upsample,
    group_norm,
    plain_conv3x3,
)
from .autoencoder_plugin import DmVqganConfig, VqganConfig


class VqganAutoencoder(Autoencoder):
    """VQGAN encoder + decoder (with optional DM-VQGAN parts)."""

    def __init__(self, config: VqganConfig, image_size: ImageSize, channels: int = 3) -> None:
        super().__init__()
        levels = len(config.channel_multipliers)
        self.downsample_factor = 2 ** (levels - 1)
        self.latent_channels = config.embed_dim
        if any(side % self.downsample_factor for side in image_hw(image_size)):
            raise ConfigError(
                f"image_size {size_text(image_size)} is not divisible by the tokenizer's downsampling "
                f"factor f = {self.downsample_factor} (channel_multipliers "
                f"{config.channel_multipliers}): use sides that are multiples of "
                f"{self.downsample_factor}"
            )
        dm = config if isinstance(config, DmVqganConfig) else None
        self.offset_lr_scale = dm.offset_lr_scale if dm else 1.0
        groups = config.norm_groups

        # Levels 0 .. levels-1 run from the image to the latent end; the middle blocks are at the last.
        first_deformable_level = levels - dm.deformable_levels if dm else levels

        def conv_at(level: int) -> ConvFactory:
            if level < first_deformable_level:
                return plain_conv3x3
            from .deformable import DeformableConv2d

            return partial(
                DeformableConv2d,
                kernel_size=3,
                padding=1,
                modulation=dm.deformable_modulation,
                max_offset=dm.max_offset,
                backend=dm.deformable_backend,
            )

        def block(in_ch: int, out_ch: int, level: int) -> ResnetBlock:
            return ResnetBlock(in_ch, out_ch, groups, config.dropout, conv_at(level))

        widths = [config.channels * m for m in config.channel_multipliers]
        # -- encoder ------------------------------------------------------------------------
        self.enc_in = nn.Conv2d(channels, config.channels, 3, padding=1)
        self.enc_levels = nn.ModuleList()
        resolution, width = min(image_hw(image_size)), config.channels
        for level, out_width in enumerate(widths):
            stage = nn.Module()
            stage.blocks = nn.ModuleList()
            stage.attentions = nn.ModuleList()
            for _ in range(config.num_res_blocks):
                stage.blocks.append(block(width, out_width, level))
                width = out_width
                stage.attentions.append(
                    AttentionBlock(width, groups) if resolution in config.attention_resolutions else nn.Identity()
                )
            stage.down = Downsample(width) if level < levels - 1 else nn.Identity()
            resolution = resolution // 2 if level < levels - 1 else resolution
            self.enc_levels.append(stage)
        self.enc_mid = self._mid(width, levels - 1, block, groups, config.mid_attention)
        self.enc_fusion = MultiScaleFusion(width, groups, dm.fusion_dilations) if dm and dm.fusion else nn.Identity()
        self.enc_norm = group_norm(width, groups)
        self.enc_out = nn.Conv2d(width, config.z_channels, 3, padding=1)
        self.quant_conv = nn.Conv2d(config.z_channels, config.embed_dim, 1)
        # -- decoder ------------------------------------------------------------------------
        self.post_quant_conv = nn.Conv2d(config.embed_dim, config.z_channels, 1)
        self.dec_in = nn.Conv2d(config.z_channels, width, 3, padding=1)
        self.dec_fusion = MultiScaleFusion(width, groups, dm.fusion_dilations) if dm and dm.fusion else nn.Identity()
        self.dec_mid = self._mid(width, levels - 1, block, groups, config.mid_attention)
        self.dec_levels = nn.ModuleList()
        for level, out_width in reversed(list(enumerate(widths))):
            stage = nn.Module()
            stage.blocks = nn.ModuleList()
            stage.attentions = nn.ModuleList()
            for _ in range(config.num_res_blocks + 1):
                stage.blocks.append(block(width, out_width, level))
                width = out_width
                stage.attentions.append(
                    AttentionBlock(width, groups) if resolution in config.attention_resolutions else nn.Identity()
                )
            stage.up = Upsample(width) if level > 0 else nn.Identity()
            resolution = resolution * 2 if level > 0 else resolution
            self.dec_levels.append(stage)
        self.dec_norm = group_norm(width, groups)
        self.dec_out = nn.Conv2d(width, channels, 3, padding=1)

    @staticmethod
    def _mid(width: int, level: int, block, groups: int, attention: bool) -> nn.Sequential:
        return nn.Sequential(
            block(width, width, level),
            AttentionBlock(width, groups) if attention else nn.Identity(),
            block(width, width, level),
        )

    def encode(self, images_BCHW: torch.Tensor) -> torch.Tensor:
        if images_BCHW.ndim != 4 or images_BCHW.shape[1] != self.enc_in.in_channels:
            raise ValueError(
                f"expected images (B, {self.enc_in.in_channels}, H, W) in [-1, 1], got {tuple(images_BCHW.shape)}"
            )
        if images_BCHW.shape[-1] % self.downsample_factor or images_BCHW.shape[-2] % self.downsample_factor:
            raise ValueError(
                f"image size {tuple(images_BCHW.shape[-2:])} is not divisible by f = {self.downsample_factor}"
            )
        h = self.enc_in(images_BCHW)
        for stage in self.enc_levels:
            for block, attention in zip(stage.blocks, stage.attentions):
                h = attention(block(h))
            h = stage.down(h)
        h = self.enc_fusion(self.enc_mid(h))
        return self.quant_conv(self.enc_out(F.silu(self.enc_norm(h))))

    def decode(self, latents_BDhw: torch.Tensor) -> torch.Tensor:
        h = self.dec_in(self.post_quant_conv(latents_BDhw.to(self.post_quant_conv.weight.dtype)))
        h = self.dec_mid(self.dec_fusion(h))
        for stage in self.dec_levels:
            for block, attention in zip(stage.blocks, stage.attentions):
                h = attention(block(h))
            h = stage.up(h)
        return self.dec_out(F.silu(self.dec_norm(h)))

    def last_layer_weight(self) -> torch.Tensor:
        return self.dec_out.weight

    def learning_rate_scales(self) -> list[tuple[float, list[nn.Parameter]]]:
        """DM-VQGAN: every deformable layer's offset/mask branch at ``offset_lr_scale``; VQGAN: none."""
        offsets = [p for m in self.modules() if hasattr(m, "offset_parameters") for p in m.offset_parameters()]
        return [(self.offset_lr_scale, offsets)] if offsets else []

    def offset_magnitude(self) -> float | None:
        """Mean |offset| of the deformable layers in the last forward (None without any)."""
        values = [
            m.last_mean_abs_offset for m in self.modules() if getattr(m, "last_mean_abs_offset", None) is not None
        ]
        return sum(values) / len(values) if values else None


def build_autoencoder(config: VqganConfig, context: BuildContext) -> VqganAutoencoder:
    """Factory for ``vqgan`` and ``dm_vqgan``."""
    return VqganAutoencoder(config, context.image_size, context.channels)

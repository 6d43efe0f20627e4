"""The ``vqgan`` and ``dm_vqgan`` autoencoders' plugin: their options and registration (the network, in
autoencoder.py, is imported when built)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from vqtouch.core import PluginConfig, hookimpl


class VqganConfig(PluginConfig):
    """Options of the ``vqgan`` autoencoder (taming-style VQGAN)."""

    name: Literal["vqgan"] = "vqgan"
    channels: int = Field(64, ge=8, le=1024, description="Base channel count (a multiple of norm_groups).")
    channel_multipliers: tuple[int, ...] = Field(
        (1, 2, 2),
        min_length=1,
        max_length=7,
        description="Channel multiplier per resolution level; f = 2 ** (levels - 1) (default f = 4).",
    )
    num_res_blocks: int = Field(1, ge=1, le=8, description="ResNet blocks per level (the decoder uses one more).")
    attention_resolutions: tuple[int, ...] = Field(
        (),
        description="Feature resolutions (the feature map's shorter side, in pixels) that get an attention "
        "block after each ResNet block.",
    )
    mid_attention: bool = Field(
        True,
        description="Attention in the middle (bottleneck) block, as in taming: over (H/f) x (W/f) tokens, "
        "4096 at 256x256 px and f = 4, so its memory grows with the image area squared; false "
        "drops it (bench/resolution_tokenizer.py measures both).",
    )
    z_channels: int = Field(64, ge=1, le=4096, description="Channels at the encoder output, before quant_conv.")
    embed_dim: int = Field(32, ge=1, le=4096, description="Latent channels fed to the quantizer (after quant_conv).")
    dropout: float = Field(0.0, ge=0.0, lt=1.0, description="Dropout inside ResNet blocks.")
    norm_groups: int = Field(32, ge=1, le=256, description="GroupNorm groups; must divide every channel count.")

    @model_validator(mode="after")
    def _channels_fit_groups(self) -> VqganConfig:
        for multiplier in self.channel_multipliers:
            if multiplier < 1 or (self.channels * multiplier) % self.norm_groups:
                raise ValueError(
                    f"channels * multiplier = {self.channels} * {multiplier} must be a positive "
                    f"multiple of norm_groups = {self.norm_groups}"
                )
        return self


class DmVqganConfig(VqganConfig):
    """Options of the ``dm_vqgan`` autoencoder: VQGAN + deformable convolutions + multi-scale fusion."""

    name: Literal["dm_vqgan"] = "dm_vqgan"
    deformable_levels: int = Field(
        2,
        ge=0,
        description="How many feature levels, counted from the latent (lowest-resolution) end, have ResNet "
        "blocks with a deformable second convolution; the middle (bottleneck) blocks belong to the "
        "lowest level.  Relative to the image, so the network is the same at every image_size: with "
        "the default channel_multipliers (1, 2, 2) and 2, the levels at 1/2 and 1/4 of the image "
        "side plus the middle blocks (10 deformable layers).  0 disables them (the ablation); at "
        "most len(channel_multipliers) (every level); each level further up costs ~4x more on CPU.",
    )
    deformable_backend: Literal["grid_sample", "gather", "torchvision"] = Field(
        "gather",
        description="Deformable convolution implementation, same maths to 1e-5: gather (channels-last "
        "bilinear gather + one matmul, pure PyTorch; the fastest measured on CPU, "
        "bench/bench_dm_vqgan.py), grid_sample (pure PyTorch) or torchvision's kernel "
        "(bench/bench_deformable.py times the three layer by layer).",
    )
    deformable_modulation: bool = Field(True, description="DCNv2 modulation mask (False: DCNv1).")
    max_offset: float = Field(4.0, gt=0.0, le=64.0, description="Offsets are bounded to max_offset * tanh(raw) pixels.")
    offset_lr_scale: float = Field(
        0.1,
        gt=0.0,
        le=10.0,
        description="Learning rate of the deformable offset/mask branches as a multiple of train.learning_rate. "
        "The offsets are amplified by max_offset, so the usual x0.1 (mmcv/mmengine) keeps early "
        "offsets from jumping; 1.0 trains them like every other weight.",
    )
    fusion: bool = Field(True, description="Multi-scale dilated fusion at the encoder output and decoder input.")
    fusion_dilations: tuple[int, ...] = Field(
        (1, 2, 4), min_length=1, max_length=6, description="Dilations of the fusion branches."
    )

    @model_validator(mode="after")
    def _deformable_levels_exist(self) -> DmVqganConfig:
        levels = len(self.channel_multipliers)
        if self.deformable_levels > levels:
            raise ValueError(
                f"deformable_levels = {self.deformable_levels} exceeds the {levels} feature level(s) "
                f"of channel_multipliers {tuple(self.channel_multipliers)}: allowed 0 to {levels}"
            )
        return self


@hookimpl
def vqtouch_register_autoencoders(register):
    # The demo trains at half the base width so it finishes in minutes on a CPU.
    register(
        "vqgan",
        "vqtouch.plugins.tokenizer.autoencoder:build_autoencoder",
        VqganConfig,
        demo={"channels": 32},
        description="VQGAN autoencoder (ResNet + GroupNorm + attention), the baseline tokenizer.",
    )
    register(
        "dm_vqgan",
        "vqtouch.plugins.tokenizer.autoencoder:build_autoencoder",
        DmVqganConfig,
        demo={"channels": 32},
        description="DM-VQGAN: VQGAN + deformable convolutions + multi-scale dilated fusion.",
    )

"""The MAE baseline's plugin: the ``mae`` autoencoder's and the ``identity`` quantizer's options and
registration (the models, in mae.py, are imported when built)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from vqtouch.core import PluginConfig, hookimpl


class MaeConfig(PluginConfig):
    """Options of the ``mae`` baseline encoder."""

    name: Literal["mae"] = "mae"
    patch_size: int = Field(8, ge=2, le=64, description="Side of the square patches (image_size must divide).")
    mask_ratio: float = Field(0.5, ge=0.0, lt=1.0, description="Fraction of patches hidden from the encoder.")
    width: int = Field(128, ge=16, le=2048, description="Width of the ViT encoder tokens.")
    depth: int = Field(4, ge=1, le=24, description="Transformer blocks in the encoder.")
    heads: int = Field(4, ge=1, le=32, description="Attention heads (must divide width).")
    decoder_width: int = Field(
        96,
        ge=16,
        le=2048,
        description="Width of the decoder tokens (the first latent channels; the latents add "
        "a visible flag and, with paste_visible, the visible patches' pixels).",
    )
    decoder_depth: int = Field(2, ge=1, le=12, description="Transformer blocks in the decoder.")
    paste_visible: bool = Field(
        True,
        description="In eval mode, copy visible patches into the reconstruction "
        "(the latents then carry the visible patches' pixels).",
    )


class IdentityConfig(PluginConfig):
    """Options of the ``identity`` quantizer (continuous latents, for baselines such as MAE)."""

    name: Literal["identity"] = "identity"


@hookimpl
def vqtouch_register_autoencoders(register):
    register(
        "mae",
        "vqtouch.plugins.tokenizer.mae:build_mae",
        MaeConfig,
        description="Masked-autoencoder ViT baseline (use with the identity "
        "quantizer; Table 1 at mask ratios 0.25/0.5/0.75).",
    )


@hookimpl
def vqtouch_register_quantizers(register):
    register(
        "identity",
        "vqtouch.plugins.tokenizer.mae:build_identity",
        IdentityConfig,
        description="No quantization (continuous latents), for baselines such as MAE.",
    )

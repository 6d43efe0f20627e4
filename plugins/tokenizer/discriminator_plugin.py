"""The ``patchgan`` discriminator's plugin: its options and registration (the network, in discriminator.py,
is imported when built)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from vqtouch.core import PluginConfig, hookimpl


class PatchGanConfig(PluginConfig):
    """Options of the ``patchgan`` discriminator."""

    name: Literal["patchgan"] = "patchgan"
    channels: int = Field(64, ge=8, le=512, description="Channels of the first layer (doubling, up to 8x).")
    layers: int = Field(3, ge=1, le=6, description="Stride-2 layers; 3 gives a 70x70 receptive field.")


@hookimpl
def vqtouch_register_discriminators(register):
    register(
        "patchgan",
        "vqtouch.plugins.tokenizer.discriminator:build_patchgan",
        PatchGanConfig,
        description="PatchGAN discriminator (4x4 convs, GroupNorm, LeakyReLU) with the hinge loss.",
    )

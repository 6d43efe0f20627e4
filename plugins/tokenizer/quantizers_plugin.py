"""The ``vq`` and ``ema_vq`` quantizers' plugin: their options and registration (the quantizers, in
quantizers.py, are imported when built)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from vqtouch.core import PluginConfig, hookimpl

CodebookInit = Literal["uniform", "normal"]


# -- configs ------------------------------------------------------------------------------------


class _CodebookConfig(PluginConfig):
    """Options every codebook quantizer has."""

    codebook_size: int = Field(1024, ge=2, le=65536, description="Number of codebook entries K.")
    embedding_dim: int = Field(
        0,
        ge=0,
        le=65536,
        description="Channels D of the latents; 0 takes the encoder's latent width from the build context.",
    )
    rotation_trick: bool = Field(
        False,
        description="Pass gradients to the encoder through the rotation and rescaling that takes each latent "
        "onto its code (Fifty et al. 2024) instead of the identity (straight-through); the forward values "
        "are the codes either way.",
    )


class VectorQuantizerConfig(_CodebookConfig):
    """Options of the ``vq`` quantizer: nearest-neighbour lookup, codebook trained by the VQ loss."""

    name: Literal["vq"] = "vq"
    beta: float = Field(
        0.25,
        ge=0.0,
        le=100.0,
        description="Commitment weight: L = ||sg[z] - e||^2 + beta * ||z - sg[e]||^2 (codebook term weight 1).",
    )
    lookup_dim: int = Field(
        0,
        ge=0,
        le=4096,
        description="0: look codes up in the full embedding_dim.  >0: factorised lookup (ViT-VQGAN): a linear "
        "map projects latents to this many dimensions, codes are found there, and a second linear "
        "map projects the chosen code back to embedding_dim (8-32 is typical).",
    )
    l2_normalize: bool = Field(
        False,
        description="Cosine-similarity lookup: latents and codes are l2-normalised before the lookup and the "
        "loss, and the quantized latents are unit-norm (ViT-VQGAN / improved VQGAN).",
    )
    init: CodebookInit = Field(
        "uniform", description="Codebook init: 'uniform' = U(-1/K, 1/K) as in taming, 'normal' = N(0, 1)."
    )
    simvq: bool = Field(
        False,
        description="SimVQ (Zhu et al. 2024): the codebook is a frozen random basis times one learned linear "
        "map (starting as the identity), so every code moves with each update and none is left unused.",
    )


class EmaVectorQuantizerConfig(_CodebookConfig):
    """Options of the ``ema_vq`` quantizer: codebook = EMA of assigned latents, dead codes restarted."""

    name: Literal["ema_vq"] = "ema_vq"
    beta: float = Field(
        0.25,
        ge=0.0,
        le=100.0,
        description="Commitment weight; the loss is beta * ||z - sg[e]||^2 only (the EMA moves the codebook).",
    )
    decay: float = Field(
        0.99,
        gt=0.0,
        lt=1.0,
        description="EMA decay of the per-code assignment counts and latent sums (memory ~ 1/(1-decay) batches).",
    )
    eps: float = Field(
        1e-5, gt=0.0, le=1.0, description="Laplace smoothing added to every EMA cluster size before dividing."
    )
    dead_threshold: float = Field(
        2.0,
        ge=0.0,
        le=1e9,
        description="A code is dead, and in training is restarted at a random latent of the current batch, when "
        "it was assigned fewer than this many latent vectors over the EMA window of ~1/(1-decay) "
        "(global) batches, i.e. when ema_cluster_size < dead_threshold * (1 - decay).  0 disables.",
    )
    init: CodebookInit = Field(
        "uniform",
        description="Codebook init before the first update: 'uniform' = U(-1/K, 1/K), 'normal' = N(0, 1).  With "
        "restarts on, codes unused in the first training batch are replaced by data anyway.",
    )


@hookimpl
def vqtouch_register_quantizers(register):
    """Register ``vq`` and ``ema_vq``."""
    register(
        "vq",
        "vqtouch.plugins.tokenizer.quantizers:build_vector_quantizer",
        VectorQuantizerConfig,
        description="Nearest-neighbour VQ, straight-through, loss ||sg[z]-e||^2 + beta||z-sg[e]||^2 "
        "(optional cosine and factorised low-dim lookup).",
    )
    register(
        "ema_vq",
        "vqtouch.plugins.tokenizer.quantizers:build_ema_vector_quantizer",
        EmaVectorQuantizerConfig,
        description="VQ with an EMA codebook, commitment loss only, and dead-code restart from the batch.",
    )

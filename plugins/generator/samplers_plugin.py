"""The samplers' plugin: the ``posterior``, ``purity`` and ``confidence`` samplers' options and registration
(the samplers, in samplers.py, are imported when built)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from vqtouch.core import PluginConfig, hookimpl


class PosteriorSamplerConfig(PluginConfig):
    """Options of the ``posterior`` sampler."""

    name: Literal["posterior"] = "posterior"
    keep_unmasked: bool = Field(
        True,
        description="Keep tokens fixed once revealed. Exact for a pure-mask schedule (an unmasked x_t was "
        "that code at every earlier step) and right for the released one (replace mass 1e-6): "
        "the posterior otherwise trusts p(x0 | x_t) for other codes and can change revealed "
        "tokens. Set false with real replace noise to follow the posterior exactly.",
    )


class PuritySamplerConfig(PluginConfig):
    """Options of the ``purity`` sampler."""

    name: Literal["purity"] = "purity"
    randomness: float = Field(
        1.0,
        ge=0.0,
        le=100.0,
        description="Scale of the Gumbel noise added to log-purity when choosing which masked tokens to reveal. "
        "1 draws the positions without replacement with probability proportional to purity "
        "(Gumbel-top-k; Improved VQ-Diffusion's purity prior); 0 is greedy (highest purity first); "
        "large values approach a uniformly random order.",
    )


class ConfidenceSamplerConfig(PluginConfig):
    """Options of the ``confidence`` sampler."""

    name: Literal["confidence"] = "confidence"
    temperature: float = Field(
        4.5,
        ge=0.0,
        le=100.0,
        description="MaskGIT's choice temperature tau: confidence = log p(sampled code) + tau (1 - (i+1)/S) "
        "Gumbel noise, so early iterations choose which tokens to keep more randomly; 4.5 as MaskGIT, "
        "0 keeps the most probable draws.",
    )


@hookimpl
def vqtouch_register_samplers(register):
    """Register the three samplers."""
    register(
        "posterior",
        "vqtouch.plugins.generator.samplers:build_posterior_sampler",
        PosteriorSamplerConfig,
        description="VQ-Diffusion reverse chain over `steps` strided timesteps, each jump an exact posterior.",
    )
    register(
        "purity",
        "vqtouch.plugins.generator.samplers:build_purity_sampler",
        PuritySamplerConfig,
        description="Improved VQ-Diffusion purity sampling: reveal the highest-purity masked tokens, "
        "a linear number per step.",
    )
    register(
        "confidence",
        "vqtouch.plugins.generator.samplers:build_confidence_sampler",
        ConfidenceSamplerConfig,
        description="MaskGIT decoding: sample all masked tokens, re-mask the least confident on a cosine "
        "schedule (temperature 4.5).",
    )

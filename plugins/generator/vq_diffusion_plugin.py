"""The ``vq_diffusion`` generator's plugin: its options and registration (the model, in vq_diffusion.py, is
imported when built)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from vqtouch.core import PluginConfig, hookimpl


class VQDiffusionConfig(PluginConfig):
    """Options of the ``vq_diffusion`` generator."""

    name: Literal["vq_diffusion"] = "vq_diffusion"
    num_steps: int = Field(
        100, ge=2, le=1000, strict=True, description="Diffusion steps T of the forward process (VQ-Diffusion uses 100)."
    )
    att_1: float = Field(0.99999, gt=0, le=1, description="alpha_bar at t = 0: probability a token is still its x0.")
    att_T: float = Field(0.000009, ge=0, le=1, description="alpha_bar at t = T-1.")
    ctt_1: float = Field(0.000009, ge=0, lt=1, description="gamma_bar at t = 0: probability a token is MASK.")
    ctt_T: float = Field(
        0.99999,
        ge=0,
        le=1,
        description="gamma_bar at t = T-1.  With the defaults (VQ-Diffusion's released values) "
        "the replace noise 1 - alpha_bar - gamma_bar is 1e-6: in effect masking only; "
        "e.g. att_T=0, ctt_T=0.9 gives replacement noise of 0.1 at the last step.",
    )
    depth: int = Field(4, ge=1, le=48, strict=True, description="Transformer blocks.")
    width: int = Field(128, ge=8, le=4096, strict=True, description="Transformer width (divisible by heads).")
    heads: int = Field(4, ge=1, le=64, strict=True, description="Attention heads.")
    mlp_ratio: float = Field(4.0, gt=0, le=16, description="MLP hidden width as a multiple of the width.")
    dropout: float = Field(0.0, ge=0, lt=1, description="Dropout in the transformer during training.")
    mlp_conv: int = Field(
        0,
        ge=0,
        le=7,
        strict=True,
        description="Kernel size of a depthwise convolution over the code grid inside every block's MLP "
        "(odd; 0: none).  Gives each code its neighbours' features through weights shared across "
        "positions: a locality prior for small data.  Measured in docs/generation.md.",
    )
    loss: Literal["vb", "masked_ce", "masked_ce_mean"] = Field(
        "masked_ce",
        description="'masked_ce': the absorbing-state (MDLM/MD4) weighted cross-entropy on masked "
        "tokens (it scored better than 'vb' on every measure at equal steps "
        "on the embedded data, see docs/results.md); 'masked_ce_mean': the mean "
        "cross-entropy of the masked tokens, every token alike whatever t (MaskGIT's "
        "objective, see docs/generation.md); 'vb': VQ-Diffusion's variational "
        "bound plus the auxiliary x0 term.",
    )
    aux_weight: float = Field(1e-3, ge=0, le=10, description="Weight of the auxiliary x0 term of the 'vb' loss.")
    contact_weight: float = Field(
        0.0,
        ge=0,
        le=100,
        description="Weight of an auxiliary loss on the aligned condition grid: a linear head on the grid's "
        "embedding (what is added to each code's token) is asked, by binary cross-entropy, which code cells "
        "hold the contact (cells whose canonical-background code is not the no-contact image's; needs "
        "generator.train.canonical_background).  Only steps whose conditioner has a grid (tactile, visual, "
        "visual_cnn), and only their non-null rows, add it; the generator stage supplies the cells "
        "(`vqtouch fewshot`'s fine-tuning does not).  0: off, no head is built.  Measured in "
        "docs/generation.md: 1 with visual_cnn and a grid context brought the visual contact "
        "1.6-2.0 px closer at equal CPU time (two training seeds); on the frozen visual grid it did nothing.",
    )
    importance_sampling: bool = Field(
        True,
        description="Draw training steps t by importance (uniform until every "
        "t was seen 10 times), as VQ-Diffusion does; else uniformly.",
    )

    @model_validator(mode="after")
    def _heads_divide_width(self) -> VQDiffusionConfig:
        if self.mlp_conv % 2 == 0 and self.mlp_conv:
            raise ValueError(f"mlp_conv must be odd (3, 5 or 7) or 0 for none; got {self.mlp_conv}")
        if self.width % self.heads:
            raise ValueError(f"width {self.width} must be divisible by heads {self.heads}")
        return self


@hookimpl
def vqtouch_register_generators(register):
    register(
        "vq_diffusion",
        "vqtouch.plugins.generator.vq_diffusion:build_vq_diffusion",
        VQDiffusionConfig,
        demo={"depth": 2, "width": 64},
        description="VQ-Diffusion style discrete diffusion over the code grid (mask-and-replace, transformer "
        "with cross-attention to the condition).",
    )

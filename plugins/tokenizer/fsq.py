"""Finite scalar quantization (``fsq``; Mentzer et al. 2023, "Finite Scalar Quantization: VQ-VAE Made
Simple"): no codebook, no codebook loss.

A linear map takes each latent vector (D channels) to ``len(levels)`` numbers; each is bounded to
``levels[i]`` values by a shifted ``tanh`` and rounded to the nearest of them, with a straight-through
gradient; a second linear map takes the rounded vector back to D channels.  The implicit codebook is
the grid of every combination, ``prod(levels)`` codes, and a code's index is its digits in mixed radix
(the first level varies fastest).  Every grid point is a code, so usage is high by construction; the
paper's levels for about 2^8, 2^10, 2^12, 2^14 and 2^16 codes are (8, 6, 5), (8, 5, 5, 5),
(7, 5, 5, 5, 5), (8, 8, 8, 6, 5) and (8, 8, 8, 5, 5, 5).

Precision: as the other quantizers, every step runs in float32 with autocast off; the quantized
latents are float32.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from vqtouch.core import BuildContext, ConfigError, Quantizer, QuantizerOutput

from .fsq_plugin import MAX_CODES, FsqConfig  # noqa: F401 - MAX_CODES re-exported: its old home
from .quantizers import _autocast_disabled, check_latents, checked_codes, perplexity_of_counts


class FiniteScalarQuantizer(Quantizer):
    """FSQ over (B, D, h, w) latents (see the module docstring); ``codebook_size = prod(levels)``."""

    def __init__(self, embedding_dim: int, levels: tuple[int, ...]) -> None:
        super().__init__()
        self.embedding_dim = embedding_dim
        self.levels = tuple(int(level) for level in levels)
        self.codebook_size = math.prod(self.levels)
        self.project_in = nn.Linear(embedding_dim, len(self.levels))
        self.project_out = nn.Linear(len(self.levels), embedding_dim)
        levels_d = torch.tensor(self.levels, dtype=torch.float32)
        radix_d = torch.cumprod(torch.tensor((1,) + self.levels[:-1], dtype=torch.long), dim=0)
        # Constants of the grid, not state: rebuilt from ``levels`` on load.
        self.register_buffer("levels_d", levels_d, persistent=False)
        #: L // 2 per dimension: digit - L // 2 is a grid point's integer value, divided by it in [-1, 1].
        self.register_buffer("half_width_d", torch.div(levels_d, 2, rounding_mode="floor"), persistent=False)
        self.register_buffer("radix_d", radix_d, persistent=False)
        self.register_buffer("usage_counts_K", torch.zeros(self.codebook_size, dtype=torch.long), persistent=False)

    # -- the grid ---------------------------------------------------------------------------------
    def _bound(self, values_Nd: torch.Tensor) -> torch.Tensor:
        """Each dimension squashed into [-(L-1)/2, (L-1)/2] (shifted by a half for even L, so rounding
        gives exactly L values)."""
        half_d = (self.levels_d - 1) * (1 + 1e-3) / 2
        offset_d = (self.levels_d % 2 == 0).float() * 0.5
        shift_d = torch.atanh(offset_d / half_d)
        return torch.tanh(values_Nd + shift_d) * half_d - offset_d

    def _digits_to_vectors(self, digits_Nd: torch.Tensor) -> torch.Tensor:
        """Digits in [0, L) to the grid's values in [-1, 1] per dimension."""
        return (digits_Nd.float() - self.half_width_d) / self.half_width_d

    # -- public API -------------------------------------------------------------------------------
    def forward(self, latents_BDhw: torch.Tensor) -> QuantizerOutput:
        """Quantise latents (B, D, h, w) of any float dtype; fp32 quantized latents, a zero loss."""
        check_latents(self, latents_BDhw)
        batch, _, height, width = latents_BDhw.shape
        with _autocast_disabled(latents_BDhw.device):
            vectors_ND = latents_BDhw.float().permute(0, 2, 3, 1).reshape(-1, self.embedding_dim)
            bounded_Nd = self._bound(F.linear(vectors_ND, self.project_in.weight.float(), self.project_in.bias.float()))
            # Straight-through, written so the forward value is exactly the grid point (lookup's value).
            rounded_Nd = bounded_Nd.detach().round() + (bounded_Nd - bounded_Nd.detach())
            digits_Nd = (rounded_Nd.detach() + self.half_width_d).long()
            codes_N = (digits_Nd * self.radix_d).sum(dim=1)
            quantized_ND = F.linear(
                rounded_Nd / self.half_width_d, self.project_out.weight.float(), self.project_out.bias.float()
            )
            with torch.no_grad():
                counts_K = torch.bincount(codes_N, minlength=self.codebook_size)
                self.usage_counts_K += counts_K
                perplexity = perplexity_of_counts(counts_K)
        quantized_BDhw = quantized_ND.view(batch, height, width, self.embedding_dim).permute(0, 3, 1, 2).contiguous()
        loss = latents_BDhw.new_zeros((), dtype=torch.float32)
        return QuantizerOutput(quantized_BDhw, codes_N.view(batch, height, width), loss, perplexity)

    def lookup(self, codes_Bhw: torch.Tensor) -> torch.Tensor:
        """Integer codes (B, h, w) in [0, K) to quantised latents (B, D, h, w) in float32."""
        codes_Bhw = checked_codes(self, codes_Bhw)
        batch, height, width = codes_Bhw.shape
        device = self.project_out.weight.device
        codes_N = codes_Bhw.to(device=device, dtype=torch.long).reshape(-1, 1)
        digits_Nd = torch.div(codes_N, self.radix_d, rounding_mode="floor") % self.levels_d.long()
        with _autocast_disabled(device):
            quantized_ND = F.linear(
                self._digits_to_vectors(digits_Nd), self.project_out.weight.float(), self.project_out.bias.float()
            )
        return quantized_ND.view(batch, height, width, self.embedding_dim).permute(0, 3, 1, 2).contiguous()

    def usage_counts(self) -> torch.Tensor:
        """(K,) how often each code was chosen since :meth:`reset_usage` (every forward call counts)."""
        return self.usage_counts_K

    def reset_usage(self) -> None:
        """Forget the usage counted so far."""
        self.usage_counts_K.zero_()

    def extra_repr(self) -> str:
        return f"levels={self.levels}, codebook_size={self.codebook_size}, embedding_dim={self.embedding_dim}"


def build_fsq(config: FsqConfig, context: BuildContext) -> FiniteScalarQuantizer:
    """Factory of ``fsq``: the latent width from the config, else from the encoder via the context."""
    embedding_dim = config.embedding_dim or context.latent_dim
    if embedding_dim < 1:
        raise ConfigError(
            "quantizer 'fsq' needs the latent width: set quantizer.embedding_dim=N or build it with the "
            "encoder's latent width in the context (BuildContext.latent_dim)"
        )
    if config.embedding_dim and context.latent_dim and config.embedding_dim != context.latent_dim:
        raise ConfigError(
            f"quantizer 'fsq': embedding_dim={config.embedding_dim} but the encoder's latents have "
            f"{context.latent_dim} channels; set embedding_dim=0 to follow the encoder"
        )
    codes = math.prod(config.levels)
    if context.codebook_size and context.codebook_size != codes:
        raise ConfigError(
            f"quantizer 'fsq': levels {list(config.levels)} make {codes} codes but the experiment expects "
            f"{context.codebook_size} (BuildContext.codebook_size); choose levels whose product is that"
        )
    return FiniteScalarQuantizer(embedding_dim, config.levels)

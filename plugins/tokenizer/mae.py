"""MAE baseline (He et al. 2022): a small ViT masked autoencoder, for the paper's Table 1.

It plugs into the tokenizer pipeline as an ``autoencoder`` with the ``identity`` quantizer:

- ``encode`` patchifies the image, hides a random ``mask_ratio`` of the patches, runs the ViT
  encoder on the visible ones only, and returns a (B, latent_channels, h, w) grid, one cell per
  patch, whose channels are
  ``[decoder tokens (decoder_width) | visible flag (1) | visible pixels (C*p*p, paste_visible only)]``:
  the visible tokens in place and a learned mask token at every hidden patch (the MAE decoder's
  input), 1 / 0 for visible / hidden, and the patch's own pixels where visible (0 where hidden);
- ``decode`` runs the light decoder over the token channels and predicts every patch's pixels.

Masking also happens in evaluation: the reported reconstruction is the image rebuilt from a
``mask_ratio`` fraction of hidden patches (visible patches pasted back unless
``paste_visible=false``), which is what MAE at 0.25 / 0.5 / 0.75 measures.  The pasted pixels
and the mask travel in the latents, so ``decode`` is a pure function of its input (it never
reads what an earlier ``encode`` saw); the extra channels carry no learned information and
need the ``identity`` quantizer.  The masks come from a generator seeded per call count in
eval mode, so evaluations are repeatable (``reset_randomness`` restarts the sequence).
"""

from __future__ import annotations

import torch
from torch import nn

from vqtouch.core import Autoencoder, BuildContext, ConfigError, Quantizer, QuantizerOutput
from vqtouch.core.image_size import ImageSize, image_hw, size_text

from .mae_plugin import IdentityConfig, MaeConfig


def _blocks(width: int, heads: int, depth: int) -> nn.TransformerEncoder:
    layer = nn.TransformerEncoderLayer(
        width, heads, 4 * width, dropout=0.0, activation="gelu", batch_first=True, norm_first=True
    )
    return nn.TransformerEncoder(layer, depth, enable_nested_tensor=False)


class MaskedAutoencoder(Autoencoder):
    """ViT masked autoencoder exposing the Autoencoder contract (see the module docstring)."""

    def __init__(self, config: MaeConfig, image_size: ImageSize, channels: int = 3) -> None:
        super().__init__()
        if any(side % config.patch_size for side in image_hw(image_size)):
            raise ConfigError(
                f"mae: image_size {size_text(image_size)} is not divisible by patch_size {config.patch_size}"
            )
        if config.width % config.heads or config.decoder_width % config.heads:
            raise ConfigError(
                f"mae: heads {config.heads} must divide width {config.width} and decoder_width {config.decoder_width}"
            )
        self.config = config
        self.channels = channels
        #: Patch rows and columns.
        self.grid_hw = tuple(side // config.patch_size for side in image_hw(image_size))
        self.downsample_factor = config.patch_size
        patch_dim = channels * config.patch_size**2
        # Latent channels: decoder tokens | visible flag | visible pixels (only when pasting them back).
        self.latent_channels = config.decoder_width + 1 + (patch_dim if config.paste_visible else 0)
        tokens = self.grid_hw[0] * self.grid_hw[1]
        self.embed = nn.Linear(patch_dim, config.width)
        self.position_LD = nn.Parameter(torch.randn(tokens, config.width) * 0.02)
        self.encoder = _blocks(config.width, config.heads, config.depth)
        self.encoder_norm = nn.LayerNorm(config.width)
        self.to_decoder = nn.Linear(config.width, config.decoder_width)
        self.mask_token_D = nn.Parameter(torch.zeros(config.decoder_width))
        self.decoder_position_LD = nn.Parameter(torch.randn(tokens, config.decoder_width) * 0.02)
        self.decoder = _blocks(config.decoder_width, config.heads, config.decoder_depth)
        self.decoder_norm = nn.LayerNorm(config.decoder_width)
        self.to_pixels = nn.Linear(config.decoder_width, patch_dim)
        self._eval_calls = 0  # the only state: which repeatable eval mask encode draws next

    def patchify(self, images_BCHW: torch.Tensor) -> torch.Tensor:
        """(B, C, H, W) -> (B, L, C*p*p) in row-major patch order."""
        batch, p, (rows, cols) = images_BCHW.shape[0], self.config.patch_size, self.grid_hw
        patches = images_BCHW.reshape(batch, self.channels, rows, p, cols, p).permute(0, 2, 4, 1, 3, 5)
        return patches.reshape(batch, rows * cols, self.channels * p * p)

    def unpatchify(self, patches_BLP: torch.Tensor) -> torch.Tensor:
        """(B, L, C*p*p) -> (B, C, H, W)."""
        batch, p, (rows, cols) = patches_BLP.shape[0], self.config.patch_size, self.grid_hw
        images = patches_BLP.reshape(batch, rows, cols, self.channels, p, p).permute(0, 3, 1, 4, 2, 5)
        return images.reshape(batch, self.channels, rows * p, cols * p)

    def _visible_mask(self, batch: int, device: torch.device) -> torch.Tensor:
        tokens = self.grid_hw[0] * self.grid_hw[1]
        keep = max(1, round(tokens * (1 - self.config.mask_ratio)))
        generator = None
        if not self.training:  # repeatable evaluation masks
            generator = torch.Generator().manual_seed(1234 + self._eval_calls)
            self._eval_calls += 1
        scores = torch.rand(batch, tokens, generator=generator).to(device)
        visible_BL = torch.zeros(batch, tokens, dtype=torch.bool, device=device)
        visible_BL.scatter_(1, scores.argsort(dim=1)[:, :keep], True)
        return visible_BL

    def encode(self, images_BCHW: torch.Tensor) -> torch.Tensor:
        height, width = (side * self.config.patch_size for side in self.grid_hw)
        if images_BCHW.ndim != 4 or tuple(images_BCHW.shape[1:]) != (self.channels, height, width):
            raise ValueError(
                f"mae expects images (B, {self.channels}, {height}, {width}), got {tuple(images_BCHW.shape)}"
            )
        batch = images_BCHW.shape[0]
        visible_BL = self._visible_mask(batch, images_BCHW.device)
        tokens_BLD = self.embed(self.patchify(images_BCHW)) + self.position_LD
        keep = int(visible_BL[0].sum())
        visible_tokens = tokens_BLD[visible_BL].view(batch, keep, -1)
        encoded = self.to_decoder(self.encoder_norm(self.encoder(visible_tokens)))
        grid_BLD = self.mask_token_D.to(encoded.dtype).expand(batch, self.grid_hw[0] * self.grid_hw[1], -1).clone()
        grid_BLD[visible_BL] = encoded.reshape(-1, encoded.shape[-1])
        # One dtype for every channel, wide enough for the tokens (bf16 under autocast) and the pixels
        # exactly: the identity quantizer and decode read them back unchanged.
        dtype = torch.promote_types(grid_BLD.dtype, images_BCHW.dtype)
        parts = [grid_BLD.to(dtype), visible_BL[..., None].to(dtype)]
        if self.config.paste_visible:
            pixels_BLP = self.patchify(images_BCHW.detach()).to(dtype)
            parts.append(
                torch.where(visible_BL[..., None], pixels_BLP, torch.zeros((), dtype=dtype, device=pixels_BLP.device))
            )
        return torch.cat(parts, dim=-1).transpose(1, 2).reshape(batch, -1, *self.grid_hw)

    def _check_latents(self, latents_BDhw: torch.Tensor) -> None:
        expected = (self.latent_channels, *self.grid_hw)
        if latents_BDhw.ndim != 4 or tuple(latents_BDhw.shape[1:]) != expected:
            raise ValueError(
                f"mae expects latents (B, {', '.join(map(str, expected))}) as encode returns them "
                f"(tokens | visible flag | visible pixels), got {tuple(latents_BDhw.shape)}"
            )

    def visible_mask(self, latents_BDhw: torch.Tensor) -> torch.Tensor:
        """(B, L) bool: which patches the encoder saw, read from the latents' visible-flag channel."""
        self._check_latents(latents_BDhw)
        return latents_BDhw[:, self.config.decoder_width].flatten(1) > 0.5

    def decode(self, latents_BDhw: torch.Tensor) -> torch.Tensor:
        """Latents from :meth:`encode` -> images; depends on nothing but ``latents_BDhw`` (and train/eval mode)."""
        self._check_latents(latents_BDhw)
        width = self.config.decoder_width
        # Split the channels in the (B, L, C) layout encode concatenated them in: the gradients then reach
        # the mask token with the same memory layout (and rounding) as before the latents carried pixels.
        cells_BLC = latents_BDhw.flatten(2).transpose(1, 2)
        tokens_BLD = cells_BLC[..., :width].to(self.decoder_position_LD.dtype)
        decoded = self.decoder_norm(self.decoder(tokens_BLD + self.decoder_position_LD))
        patches_BLP = self.to_pixels(decoded)
        if not self.training and self.config.paste_visible:
            visible_BL = self.visible_mask(latents_BDhw)
            original = cells_BLC[..., width + 1 :].to(patches_BLP.dtype)
            patches_BLP = torch.where(visible_BL[..., None], original, patches_BLP)
        return self.unpatchify(patches_BLP)

    def last_layer_weight(self) -> torch.Tensor:
        return self.to_pixels.weight

    def reset_randomness(self) -> None:
        self._eval_calls = 0


class IdentityQuantizer(Quantizer):
    """Passes latents through unchanged: zero loss, a single 'code', perplexity 1."""

    codebook_size = 1

    def __init__(self, embedding_dim: int) -> None:
        super().__init__()
        self.embedding_dim = embedding_dim

    def forward(self, latents_BDhw: torch.Tensor) -> QuantizerOutput:
        batch, _, height, width = latents_BDhw.shape
        zero = latents_BDhw.new_zeros((), dtype=torch.float32)
        codes = torch.zeros(batch, height, width, dtype=torch.long, device=latents_BDhw.device)
        return QuantizerOutput(latents_BDhw.float(), codes, zero, zero + 1)

    def lookup(self, codes_Bhw: torch.Tensor) -> torch.Tensor:
        raise ValueError("the identity quantizer has no codebook: its latents cannot be rebuilt from codes")


def build_mae(config: MaeConfig, context: BuildContext) -> MaskedAutoencoder:
    """Factory for ``mae``."""
    return MaskedAutoencoder(config, context.image_size, context.channels)


def build_identity(config: IdentityConfig, context: BuildContext) -> IdentityQuantizer:
    """Factory for ``identity`` (its width comes from the encoder via the context)."""
    return IdentityQuantizer(context.latent_dim)

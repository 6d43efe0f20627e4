"""``tactile_codes``: a conditioning tactile image as its codes under its own sensor's tokenizer.

VQ-Touch's tactile condition: the source image (by default a sample's ``tactile_source``, the
same contact seen by the experiment's ``paired_sensor``) is tokenized by a tokenizer trained on
*that* sensor's images (another run, e.g. a GelSight reconstruction run for GelSight -> DIGIT),
and its code grid is embedded: one learned vector per code plus one per grid cell.  The source
tokenizer is frozen and kept out of this conditioner's checkpoints (it is reloaded from
``tokenizer`` when the conditioner is rebuilt), so the run needs that folder where it was.

Compare ``tactile``: a CNN trained from scratch on the source image's pixels, which needs no
second tokenizer.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from vqtouch.core import BuildContext, Conditioner, ConfigError, VqtouchError, load_plugins
from vqtouch.core.image_size import ImageSize, image_hw
from vqtouch.plugins.utils.frozen import FrozenModule
from vqtouch.plugins.tokenizer import load_tokenizer

from .tactile_codes_plugin import TactileCodesConditionerConfig


class TactileCodesConditioner(Conditioner):
    """Source images (B, 3, H, W) in [0, 1] -> the frozen source tokenizer's codes (B, h, w) ->
    tokens (B, h*w, cond_dim): a code embedding plus a learned position embedding per cell."""

    def __init__(self, tokenizer: object, sample_key: str, cond_dim: int, image_size: ImageSize) -> None:
        """``tokenizer``: the source sensor's trained tokenizer (``encode_codes``; frozen here)."""
        tokenizer.autoencoder.eval().requires_grad_(False)
        tokenizer.quantizer.eval().requires_grad_(False)
        with torch.no_grad():
            grid_hw = tuple(tokenizer.encode_codes(torch.zeros(1, 3, *image_hw(image_size))).shape[1:])
        super().__init__(cond_dim, grid_hw[0] * grid_hw[1])
        self.source = tokenizer
        self.sample_key = sample_key
        self.grid_hw = grid_hw
        self.num_codes = tokenizer.quantizer.codebook_size
        # Frozen and unregistered: out of state_dict and parameters(), moved with .to() all the same.
        self.frozen_tokenizer = FrozenModule(
            nn.ModuleDict({"autoencoder": tokenizer.autoencoder, "quantizer": tokenizer.quantizer})
        )
        self.code_embedding = nn.Embedding(self.num_codes, cond_dim)
        nn.init.normal_(self.code_embedding.weight, std=0.02)
        self.position_ND = nn.Parameter(torch.randn(self.num_tokens, cond_dim) * 0.02)

    @torch.no_grad()
    def source_codes(self, images_B3HW: torch.Tensor) -> torch.Tensor:
        """The source tokenizer's codes (B, h, w) of images in [0, 1]."""
        if images_B3HW.ndim != 4 or images_B3HW.shape[1] != 3:
            raise ValueError(f"tactile_codes expects images (B, 3, H, W), got {tuple(images_B3HW.shape)}")
        # The tokenizer's own precision: the codes must not depend on an enclosing autocast.
        with torch.autocast(images_B3HW.device.type, enabled=False):
            codes_Bhw = self.source.encode_codes(images_B3HW.float())
        if tuple(codes_Bhw.shape[1:]) != self.grid_hw:
            raise ValueError(
                f"the source tokenizer made {tuple(codes_Bhw.shape[1:])} code grids from "
                f"{tuple(images_B3HW.shape[2:])} images; this conditioner was built for {self.grid_hw}"
            )
        return codes_Bhw

    def encode(self, condition: torch.Tensor) -> torch.Tensor:
        """Images (B, 3, H, W) in [0, 1] to tokens (B, h*w, cond_dim)."""
        codes_BN = self.source_codes(condition).flatten(1).to(self.code_embedding.weight.device)
        return self.code_embedding(codes_BN) + self.position_ND

    def extra_repr(self) -> str:
        return f"sample_key={self.sample_key!r}, grid={self.grid_hw}, num_codes={self.num_codes}"


def build_tactile_codes_conditioner(
    config: TactileCodesConditionerConfig, context: BuildContext
) -> TactileCodesConditioner:
    """Factory: loads the source sensor's tokenizer from ``config.tokenizer`` (frozen, on the CPU;
    the generator's ``.to(device)`` moves it) and sizes the tokens by its code grid at the
    experiment's image size."""

    if config.tokenizer is None:
        raise ConfigError(
            "conditioner 'tactile_codes' needs the source sensor's tokenizer: set "
            "generator.conditioners.N.tokenizer=RUN (a run whose tokenizer stage trained on that sensor)"
        )
    path = Path(config.tokenizer).expanduser()
    if not path.exists():
        raise ConfigError(
            f"conditioner 'tactile_codes': tokenizer {config.tokenizer} does not exist; train the source "
            "sensor's tokenizer (vqtouch train tokenizer --set sensor.name=... --out RUN) and set "
            "tokenizer=RUN"
        )
    try:
        tokenizer, _ = load_tokenizer(path, load_plugins())
    except VqtouchError as exc:
        raise ConfigError(f"conditioner 'tactile_codes': cannot load the tokenizer in {path}: {exc}") from None
    return TactileCodesConditioner(tokenizer, config.reads, context.cond_dim, context.image_size)

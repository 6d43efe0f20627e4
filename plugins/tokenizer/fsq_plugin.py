"""The ``fsq`` quantizer's plugin: its options and registration (the quantizer, in fsq.py, is imported when
built)."""

from __future__ import annotations

import math
from typing import Literal

from pydantic import Field, field_validator

from vqtouch.core import PluginConfig, hookimpl

#: Codes a generator over the grid can address (the ``vq`` quantizers' bound too).
MAX_CODES = 65536


class FsqConfig(PluginConfig):
    """Options of the ``fsq`` quantizer."""

    name: Literal["fsq"] = "fsq"
    levels: tuple[int, ...] = Field(
        (8, 5, 5, 5),
        min_length=1,
        max_length=16,
        description="Values per dimension of the code vector (each 2-256; the codebook has their product, at "
        "most 65536, codes).  The paper's choices: (8, 6, 5), (8, 5, 5, 5), (7, 5, 5, 5, 5), (8, 8, 8, 6, 5), "
        "(8, 8, 8, 5, 5, 5).",
    )
    embedding_dim: int = Field(
        0,
        ge=0,
        le=65536,
        description="Channels D of the latents; 0 takes the encoder's latent width from the build context.",
    )

    @field_validator("levels")
    @classmethod
    def _levels_in_range(cls, levels: tuple[int, ...]) -> tuple[int, ...]:
        if any(not 2 <= level <= 256 for level in levels):
            raise ValueError(f"every level must be in [2, 256], got {list(levels)}")
        if math.prod(levels) > MAX_CODES:
            raise ValueError(f"levels {list(levels)} make {math.prod(levels)} codes; at most {MAX_CODES}")
        return levels


@hookimpl
def vqtouch_register_quantizers(register):
    """Register ``fsq``."""
    register(
        "fsq",
        "vqtouch.plugins.tokenizer.fsq:build_fsq",
        FsqConfig,
        description="Finite scalar quantization: a bounded, rounded low-dimensional projection; "
        "prod(levels) codes, no codebook loss.",
    )

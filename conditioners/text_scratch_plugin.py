"""The text_scratch conditioner's plugin: its options and registration
(the model, in text_scratch.py, is imported when built)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from vqtouch.core import PluginConfig, hookimpl


class TextScratchConditionerConfig(PluginConfig):
    """Options of the ``text_scratch`` conditioner."""

    name: Literal["text_scratch"] = "text_scratch"
    vocab_buckets: int = Field(
        4096,
        ge=2,
        le=1_048_576,
        description="Hash buckets (embedding rows) words are hashed into; more buckets, fewer collisions.",
    )
    max_words: int = Field(
        16,
        ge=1,
        le=512,
        description="Words kept per text (later words are dropped); also the number of condition tokens.",
    )
    width: int = Field(128, ge=8, le=2048, description="Width of the word embeddings and of the transformer.")
    depth: int = Field(2, ge=1, le=24, description="Transformer encoder layers.")
    heads: int = Field(4, ge=1, le=64, description="Attention heads per layer; must divide width.")

    @model_validator(mode="after")
    def _heads_divide_width(self) -> TextScratchConditionerConfig:
        if self.width % self.heads:
            raise ValueError(f"heads={self.heads} must divide width={self.width}")
        return self


@hookimpl
def vqtouch_register_conditioners(register):
    register(
        "text_scratch",
        "vqtouch.conditioners.text_scratch:build_text_scratch_conditioner",
        TextScratchConditionerConfig,
        description="Hashed-word embeddings + small transformer trained from scratch, offline, no vocabulary "
        "file (text-to-touch).",
    )

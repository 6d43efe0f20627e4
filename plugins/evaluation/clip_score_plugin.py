"""The ``clip_score`` metric's plugin: its options and registration (the metric, in clip_score.py, is imported
when built)."""

from __future__ import annotations

import string
from typing import Any, Literal

from pydantic import Field, field_validator

from vqtouch.core import PluginConfig, hookimpl


class ClipScoreConfig(PluginConfig):
    """Options of the ``clip_score`` metric (CLIP-space consistency of generated images with their conditions)."""

    name: Literal["clip_score"] = "clip_score"
    architecture: str = Field(
        "ViT-B-32",
        min_length=1,
        description="open_clip model name whose weights the checkpoint file holds; texts and "
        "labels need its built-in BPE tokenizer (e.g. ViT-B-32, ViT-L-14).",
    )
    checkpoint: str | None = Field(
        None,
        description="Path to the open_clip weights (.safetensors/.pt/.bin; the whole model, as for the clip "
        "conditioner); else VQTOUCH_CLIP_CKPT or VQTOUCH_WEIGHTS_DIR. Never downloaded: without "
        "it the metric is reported as skipped.",
    )
    prompt: str = Field(
        "a tactile sensor image of {label}",
        min_length=1,
        description="Text a label condition is embedded as: {label} is replaced by the class name.",
    )
    model_overrides: dict[str, Any] = Field(
        default_factory=dict,
        description="Keyword overrides passed to open_clip.create_model (e.g. a small "
        "vision_cfg for a custom-trained model); must match the checkpoint.",
    )
    batch_size: int = Field(32, ge=1, le=1024, description="Images or texts per CLIP forward pass.")

    @field_validator("prompt")
    @classmethod
    def _one_label_placeholder(cls, prompt: str) -> str:
        """A prompt must name the class exactly once, as {label}, and nothing else str.format would fill."""
        try:
            fields = [field for _, field, _, _ in string.Formatter().parse(prompt) if field is not None]
        except ValueError as error:
            raise ValueError(
                f"prompt {prompt!r} is not a format string ({error}); write e.g. 'a tactile sensor image of {{label}}'"
            ) from None
        if fields != ["label"]:
            raise ValueError(
                f"prompt {prompt!r} must contain {{label}} exactly once and no other {{...}} field, "
                "e.g. 'a tactile sensor image of {label}'"
            )
        return prompt


@hookimpl
def vqtouch_register_metrics(register: Any) -> None:
    """Register the ``clip_score`` metric (the metric hook; the entry point is in pyproject.toml)."""
    register(
        "clip_score",
        "vqtouch.plugins.evaluation.clip_score:build_clip_score",
        ClipScoreConfig,
        description="CLIP-space cosine between generated tactile images and their conditions (image, text, "
        "label prompt), with an open_clip checkpoint from a local file; skipped without it.",
    )

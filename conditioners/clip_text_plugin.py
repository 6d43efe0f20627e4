"""The text conditioner's plugin: its options and registration (the model, in clip_text.py, is imported when built)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field

from vqtouch.core import PluginConfig, hookimpl


class TextConditionerConfig(PluginConfig):
    """Options of the ``text`` conditioner (frozen open_clip text tower from a local file)."""

    name: Literal["text"] = "text"
    architecture: str = Field(
        "ViT-B-32",
        min_length=1,
        description="open_clip model name whose weights the checkpoint file holds; its "
        "tokenizer must be open_clip's built-in BPE tokenizer (no Hugging Face "
        "tokenizer, which would be downloaded).",
    )
    checkpoint: str | None = Field(
        None,
        description="Path to the open_clip weights (.safetensors/.pt/.bin; the whole model, as for the clip "
        "conditioner); else VQTOUCH_CLIP_CKPT or VQTOUCH_WEIGHTS_DIR. Never downloaded.",
    )
    context_length: int = Field(
        32,
        ge=2,
        le=77,
        description="Text token positions kept, start- and end-of-text included, which is also the number of "
        "condition tokens: each is the frozen text transformer's final hidden state at that position, "
        "projected to cond_dim by a trainable linear layer. Longer texts are truncated (the last kept "
        "position becomes end-of-text); at most the model's own context length (77 for CLIP).",
    )
    model_overrides: dict[str, Any] = Field(
        default_factory=dict,
        description="Keyword overrides passed to open_clip.create_model (e.g. a small "
        "text_cfg for a custom-trained model); must match the checkpoint.",
    )


@hookimpl
def vqtouch_register_conditioners(register):
    """Register the ``text`` conditioner (the conditioner hook; the entry point is in pyproject.toml)."""
    register(
        "text",
        "vqtouch.conditioners.clip_text:build_text_conditioner",
        TextConditionerConfig,
        description="Frozen open_clip text tower from a local file, per-token final hidden states + trainable "
        "projection (text-to-touch).",
    )

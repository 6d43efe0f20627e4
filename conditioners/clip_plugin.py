"""The clip conditioner's plugin: its options and registration (the model, in clip.py, is imported when built)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field

from vqtouch.core import PluginConfig, hookimpl


class ClipConditionerConfig(PluginConfig):
    """Options of the ``clip`` conditioner."""

    name: Literal["clip"] = "clip"
    architecture: str = Field(
        "ViT-B-32", min_length=1, description="open_clip model name whose weights the checkpoint file holds."
    )
    checkpoint: str | None = Field(
        None,
        description="Path to the open_clip weights (.safetensors/.pt/.bin); else VQTOUCH_CLIP_CKPT or "
        "VQTOUCH_WEIGHTS_DIR. Never downloaded.",
    )
    num_tokens: int = Field(4, ge=1, le=77, description="Condition tokens projected from the image embedding.")
    model_overrides: dict[str, Any] = Field(
        default_factory=dict,
        description="Keyword overrides passed to open_clip.create_model (e.g. a small "
        "vision_cfg for a custom-trained model); must match the checkpoint.",
    )


@hookimpl
def vqtouch_register_conditioners(register):
    register(
        "clip",
        "vqtouch.conditioners.clip:build_clip_conditioner",
        ClipConditionerConfig,
        description="Frozen open_clip image encoder from a local file + trainable projection (vision-to-touch).",
    )

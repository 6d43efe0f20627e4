"""The label conditioner's plugin: its options and registration (the model, in label.py, is imported when built)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from vqtouch.core import PluginConfig, hookimpl


class LabelConditionerConfig(PluginConfig):
    """Options of the ``label`` conditioner."""

    name: Literal["label"] = "label"
    num_classes: int = Field(
        0, ge=0, le=1_000_000, description="Number of labels; 0 takes the dataset's count from the build context."
    )
    num_tokens: int = Field(1, ge=1, le=64, description="Condition tokens emitted per label.")


@hookimpl
def vqtouch_register_conditioners(register):
    register(
        "label",
        "vqtouch.conditioners.label:build_label_conditioner",
        LabelConditionerConfig,
        description="Learned embedding tokens per class label (label-to-touch).",
    )

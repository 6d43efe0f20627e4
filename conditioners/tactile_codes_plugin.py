"""The tactile_codes conditioner's plugin: its options and registration
(the model, in tactile_codes.py, is imported when built)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from vqtouch.core import PluginConfig, hookimpl


class TactileCodesConditionerConfig(PluginConfig):
    """Options of the ``tactile_codes`` conditioner."""

    name: Literal["tactile_codes"] = "tactile_codes"
    tokenizer: str | None = Field(
        None,
        min_length=1,
        description="The source sensor's tokenizer: a run directory whose tokenizer stage trained (its newest good "
        "checkpoint) or a checkpoint folder holding autoencoder.safetensors and quantizer.safetensors.",
    )
    reads: Literal["tactile_source", "tactile"] = Field(
        "tactile_source",
        description="Sample entry encoded: 'tactile_source' (the paired sensor's image of the same "
        "contact) or 'tactile' (the target image itself: a sanity check, not a task).",
    )


@hookimpl
def vqtouch_register_conditioners(register):
    register(
        "tactile_codes",
        "vqtouch.conditioners.tactile_codes:build_tactile_codes_conditioner",
        TactileCodesConditionerConfig,
        description="A source tactile image as its codes under its own sensor's frozen tokenizer, embedded "
        "(VQ-Touch's touch-to-touch condition).",
    )

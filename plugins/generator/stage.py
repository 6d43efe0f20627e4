"""The ``generator`` stage's section and slots.

The stage generates code grids for the trained tokenizer, conditioned on one of several
conditioners (the paper's unified framework trains with one condition per step).  Its
section declares the generator plugin and the list of conditioners, so scenes and
configs that name them validate today; training and sampling are not implemented in this
version, and the stage says so when asked to run.
"""

from __future__ import annotations

from typing import Any

from pydantic import Field

from vqtouch.core import Section, Slot, StageJob, StageUnavailable, hookimpl


class GeneratorSection(Section):
    """The ``generator`` stage's section: the generator plugin and its conditioners."""

    model: Slot("generator") | None = Field(None, description="Generator over the code grid (e.g. a discrete "
                                                               "diffusion decoder).")
    conditioners: list[Slot("conditioner")] = Field(
        default_factory=list, description="Condition encoders the generator is trained with (label, tactile, "
                                          "clip, ...); each reads its own entry of a sample.")


def run_generator_stage(job: StageJob) -> dict[str, Any]:
    """Not implemented in this version: says so (after the slots were checked)."""
    raise StageUnavailable("training the generator is not implemented in this version of vqtouch (its section, "
                           "generator.model and generator.conditioners, is declared and validated)")


@hookimpl
def vqtouch_register_stages(register):
    register("generator", run_generator_stage, section=GeneratorSection,
             needs=("data.dataset", "tokenizer.autoencoder", "tokenizer.quantizer", "generator.model",
                    "generator.conditioners"),
             uses=("metrics",),
             description="Train a generator over the tokenizer's codes, conditioned on a visual image, a tactile "
                         "image, a label or text.")

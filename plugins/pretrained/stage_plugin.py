"""The ``pretrained`` stage's plugin: its section, its registration and the ``pretrained:NAME`` opener (the
stage, in stage.py, and the bundles, in bundle.py, are imported when used)."""

from __future__ import annotations

from pydantic import Field

from vqtouch.core import Section, hookimpl


class PretrainedSection(Section):
    """The ``pretrained`` stage's options."""

    bundle: str = Field("tour", description="Name of the bundled checkpoints to show (`vqtouch pretrained list`).")
    num_samples: int = Field(
        16,
        ge=1,
        le=10_000,
        strict=True,
        description="Held-out images reconstructed and held-out conditions generated per "
        "conditioner (at most the held-out split).",
    )
    sampler: str = Field("posterior", description="Sampler plugin the bundled generator draws codes with.")
    steps: int = Field(25, ge=1, le=1000, strict=True, description="Sampling steps per generated image.")


@hookimpl
def vqtouch_open_pretrained(name, host, device, tokenizer_only):
    """Open a bundle of this package for ``pretrained:NAME`` (the generation pipeline and the family
    stages ask)."""
    from .bundle import load_bundle  # torch, imported only when a bundle is opened

    return load_bundle(name, host, device=device, tokenizer_only=tokenizer_only)


@hookimpl
def vqtouch_register_stages(register):
    register(
        "pretrained",
        "vqtouch.plugins.pretrained.stage:run_pretrained_stage",
        section=PretrainedSection,
        needs=("data.dataset",),
        uses=("metrics", "sensor"),
        demo={"num_samples": 8, "steps": 10},
        description="Show the bundled pretrained tokenizer and generator (trained longer than a demo can, "
        "shipped in the package) on this run's held-out data: reconstructions and generations "
        "from every condition, scored beside the background; nothing is trained.",
    )

"""Building the components an experiment needs, and nothing more.

A scene's stages decide which slots are required (``STAGE_SLOTS``); only those slots
are built, so a label-conditioned run never imports CLIP and a reconstruction run never
builds a generator.
"""

from __future__ import annotations

from typing import Any

from .components import BuildContext, Encoder, Quantizer, TactileDataset
from .config import SLOT_KINDS, ExperimentConfig
from .errors import ConfigError


def build_context(config: ExperimentConfig, **facts: Any) -> BuildContext:
    """The BuildContext of an experiment; ``facts`` (e.g. ``num_classes``) come from the data."""
    sensor = config.sensor.model_dump(mode="json") if config.sensor is not None else None
    return BuildContext(image_size=config.data.image_size, sensor=sensor, **facts)


def enrich_context(context: BuildContext, component: Any) -> BuildContext:
    """The context after ``component`` is built: later components see what it determines.

    A dataset fixes the number of classes, an encoder the latent width the quantizer must
    match, and a quantizer the codebook size the generator works with.
    """
    if isinstance(component, TactileDataset):
        return context.model_copy(update={"num_classes": component.num_classes})
    if isinstance(component, Encoder):
        return context.model_copy(update={"latent_dim": component.latent_channels})
    if isinstance(component, Quantizer):
        return context.model_copy(update={"codebook_size": component.codebook_size})
    return context


def build_components(config: ExperimentConfig, host: Any, *, slots: list[str] | None = None,
                     context: BuildContext | None = None) -> dict[str, Any]:
    """Build the components of ``slots`` (default: the slots the config's stages require).

    Returns ``{slot_path: component}``; list slots (``metrics``) map to a list.  A
    required slot left empty raises ConfigError naming the stage and the choices.
    """
    context = context or build_context(config)
    slots = config.required_slots() if slots is None else slots
    missing: dict[str, str] = {}
    for stage, path in config.missing_slots():
        if path in slots:
            missing.setdefault(path, stage)
    if missing:
        path, stage = next(iter(missing.items()))
        kind = SLOT_KINDS[path]
        choices = ", ".join(host.registry(kind).names()) or f"none installed yet (no {kind} plugin)"
        raise ConfigError(f"stage {stage!r} needs {path} but the config leaves it empty; "
                          f"set {path}.name to one of: {choices}")
    built: dict[str, Any] = {}
    # Data first, then the encoder, then the rest: each may fix facts the next ones need.
    for path in sorted(slots, key=lambda p: (p != "data.dataset", p != "tokenizer.encoder")):
        value = config.slot(path)
        kind = SLOT_KINDS[path]
        if isinstance(value, list):
            built[path] = [host.build(kind, item, context) for item in value]
        elif value is not None:
            built[path] = host.build(kind, value, context)
            context = enrich_context(context, built[path])
    return {path: built[path] for path in slots if path in built}

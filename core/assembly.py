"""Building the components an experiment needs, and nothing more.

A scene's stages decide which slots are required (``STAGE_SLOTS``); only those slots
are built, so a label-conditioned run never imports CLIP and a reconstruction run never
builds a generator.
"""

from __future__ import annotations

from typing import Any

from .components import BuildContext
from .config import SLOT_KINDS, ExperimentConfig
from .errors import ConfigError


def build_context(config: ExperimentConfig, **facts: Any) -> BuildContext:
    """The BuildContext of an experiment; ``facts`` (e.g. ``num_classes``) come from the data."""
    sensor = config.sensor.model_dump(mode="json") if config.sensor is not None else None
    return BuildContext(image_size=config.data.image_size, sensor=sensor, **facts)


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
    for path in slots:
        value = config.slot(path)
        kind = SLOT_KINDS[path]
        if isinstance(value, list):
            built[path] = [host.build(kind, item, context) for item in value]
        elif value is not None:
            built[path] = host.build(kind, value, context)
    return built

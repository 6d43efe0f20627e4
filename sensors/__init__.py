"""Sensor families: the built-in ones (GelSight, GelSight Mini, DIGIT) and the public API for writing more.

A third-party sensor family subclasses :class:`RenderedSensor` (background + contact
response + optional :meth:`~RenderedSensor.surface_effects`, with full :class:`SensorVariant`
support) and registers a factory through the ``vqtouch_register_sensor_families`` hook::

    from vqtouch.core import PluginConfig, hookimpl
    from vqtouch.sensors import RenderedSensor, SensorVariant, surface_slopes

Import only from ``vqtouch.sensors`` (this module) and ``vqtouch.core``: the sub-modules
(``vqtouch.sensors.base``, ``.variants``, ...) are internal and may move.  The built-in
families themselves are plugins loaded through entry points; they are not imported here,
so this import stays light (no calibration data, no numpy file reads).
"""

from __future__ import annotations

import importlib
from typing import Any

#: Public name -> (module of this package, name there); imported on first use, so that importing this
#: package (as every built-in family's plugin module does) imports no torch.
_PUBLIC = {
    "RenderedSensor": ("base", "RenderedSensor"),
    "SensorVariant": ("variant_options", "SensorVariant"),
    "apply_variant": ("variants", "apply_variant"),
    "check_height_map": ("base", "check_height_map"),
    "drifted_background": ("variants", "drifted_background"),
    "environment_variant": ("variants", "environment_variant"),
    "gaussian_blur": ("variants", "gaussian_blur"),
    "surface_slopes": ("base", "surface_slopes"),
}

__all__ = sorted(_PUBLIC)


def __getattr__(name: str) -> Any:
    if name not in _PUBLIC:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    module, attribute = _PUBLIC[name]
    value = getattr(importlib.import_module(f"{__name__}.{module}"), attribute)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_PUBLIC])

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

from .base import RenderedSensor, check_height_map, surface_slopes
from .variants import SensorVariant, apply_variant, drifted_background, environment_variant, gaussian_blur

__all__ = [
    "RenderedSensor",
    "SensorVariant",
    "apply_variant",
    "check_height_map",
    "drifted_background",
    "environment_variant",
    "gaussian_blur",
    "surface_slopes",
]

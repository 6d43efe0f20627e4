"""The sensor tag's plugin: its options and registration (the model, in sensor.py, is imported when built)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from vqtouch.core import PluginConfig, hookimpl


class SensorTagConfig(PluginConfig):
    """Options of the ``sensor`` conditioner (``generator.sensor_tag``)."""

    name: Literal["sensor"] = "sensor"
    num_sensors: int = Field(2, ge=1, le=1024, description="How many sensors the generator tells apart.")
    sensor_names: list[str] = Field(
        default_factory=list, description="What each sensor index is (for reading runs); may be empty."
    )


@hookimpl
def vqtouch_register_conditioners(register):
    register(
        "sensor",
        "vqtouch.conditioners.sensor:build_sensor_tag",
        SensorTagConfig,
        description="A learned offset per sensor added to every condition (generator.sensor_tag; vqtouch fewshot).",
    )

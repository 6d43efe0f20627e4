"""Sensor tag: one learned offset per sensor, added to every condition's tokens.

One generator can then draw several sensors' appearance from the same conditions: ``vqtouch
fewshot`` fine-tunes a family's generator on the family's data (sensor 0) mixed with a few images
of an unseen sensor (sensor 1), and samples with sensor 1's offset.  The offsets start at zero, so
a generator that has just gained a tag computes exactly what it did before; the tag is not one of
``generator.conditioners`` (a step trains one condition, and every condition carries the tag), but
``generator.sensor_tag``.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from vqtouch.core import BuildContext, Conditioner, ConfigError

from .sensor_plugin import SensorTagConfig


class SensorTag(Conditioner):
    """Sensor indices (B,) to an offset (B, 1, cond_dim) that :func:`add_sensor_offset` adds to
    every token of a condition (and to the null condition's, so guidance contrasts the condition
    alone, never the sensor)."""

    sample_key = "sensor_index"

    def __init__(self, num_sensors: int, cond_dim: int, sensor_names: list[str] | None = None) -> None:
        super().__init__(cond_dim, 1)
        self.num_sensors = num_sensors
        self.sensor_names = list(sensor_names or [])
        self.offsets_SD = nn.Parameter(torch.zeros(num_sensors, cond_dim))

    def encode(self, condition: Any) -> torch.Tensor:
        """Sensor indices (B,) in [0, num_sensors) to offsets (B, 1, cond_dim)."""
        sensors_B = torch.as_tensor(condition, device=self.offsets_SD.device)
        if sensors_B.dtype.is_floating_point or sensors_B.dtype == torch.bool or sensors_B.ndim != 1:
            raise ValueError(
                f"sensor indices must be a 1-D integer tensor, got {sensors_B.dtype} {tuple(sensors_B.shape)}"
            )
        if sensors_B.numel() and (sensors_B.min() < 0 or sensors_B.max() >= self.num_sensors):
            raise ValueError(
                f"sensor indices must be in [0, {self.num_sensors}); got {int(sensors_B.min())}..{int(sensors_B.max())}"
            )
        return self.offsets_SD[sensors_B.long()].unsqueeze(1)


def build_sensor_tag(config: SensorTagConfig, context: BuildContext) -> SensorTag:
    """Factory: the token width is the generator's (the build context's cond_dim)."""
    if config.sensor_names and len(config.sensor_names) != config.num_sensors:
        raise ConfigError(
            f"sensor tag: {len(config.sensor_names)} sensor_names for num_sensors={config.num_sensors}; "
            "give one name per sensor or none"
        )
    return SensorTag(config.num_sensors, context.cond_dim, config.sensor_names)

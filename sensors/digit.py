"""DIGIT-style sensor: a photometric model written for vqtouch (no measured calibration ships).

Three coloured LEDs (red, green, blue) light the gel from the sides at a low elevation,
120 degrees apart.  The camera sees:

- a background: a base level plus each LED's colour falling off with distance from the
  LED's side of the gel, and lens vignetting;
- a contact response: for each LED, the change in Lambertian shading of the deformed
  surface relative to the flat gel, ``gain * colour_k * (n . l_k - n_flat . l_k)``, so a flat
  gel shows only the background.

The parameters are plausible defaults, not a fit to a real DIGIT; use a variant to model
an individual sensor.
"""

from __future__ import annotations

import math
from typing import Literal

import torch
from pydantic import Field

from vqtouch.core import BuildContext, PluginConfig, hookimpl

from .base import RenderedSensor, surface_slopes
from .variants import SensorVariant

LED_COLOURS = ((1.0, 0.15, 0.1), (0.1, 1.0, 0.2), (0.15, 0.25, 1.0))


class DigitConfig(PluginConfig):
    """Options of the ``digit`` sensor family (photometric model)."""

    name: Literal["digit"] = "digit"
    field_of_view_mm: float = Field(16.0, ge=4.0, le=60.0, description="Side of the imaged gel square in mm.")
    led_elevation_deg: float = Field(25.0, ge=5.0, le=85.0, description="Elevation of the three LEDs above the gel.")
    led_azimuth_deg: float = Field(90.0, ge=-180.0, le=180.0,
                                   description="Azimuth of the red LED; green and blue follow at +120 and +240.")
    response_gain: float = Field(0.9, ge=0.0, le=5.0, description="Strength of the contact shading.")
    background_level: float = Field(0.42, ge=0.0, le=1.0, description="Base intensity of the unlit gel.")
    led_glow: float = Field(0.25, ge=0.0, le=1.0, description="Brightness of each LED's glow at its gel edge.")
    vignetting: float = Field(0.25, ge=0.0, le=1.0, description="Darkening at the image corners.")
    gel_blur_mm: float = Field(0.25, ge=0.0, le=2.0, description="Gaussian smoothing of the indentation in mm.")
    variant: SensorVariant = Field(default_factory=SensorVariant,
                                   description="Environmental perturbations making this a derived sensor.")


class DigitSensor(RenderedSensor):
    """Three-LED Lambertian renderer of a DIGIT-style sensor.

    ``field_of_view_mm`` comes from the config; ``sensor_id`` is ``"digit"``.  No real DIGIT
    frames ship, so :meth:`reference_frames` is the contract's default (None).
    """

    sensor_id = "digit"

    def __init__(self, config: DigitConfig) -> None:
        super().__init__(config.variant, config.gel_blur_mm)
        self.config = config
        self.field_of_view_mm = config.field_of_view_mm
        elevation = math.radians(config.led_elevation_deg)
        azimuths = [math.radians(config.led_azimuth_deg + 120 * k) for k in range(3)]
        # Light directions (x = column, y = row, z = towards the camera), one per LED.
        directions = [(math.cos(a) * math.cos(elevation), math.sin(a) * math.cos(elevation), math.sin(elevation))
                      for a in azimuths]
        self.register_buffer("light_L3", torch.tensor(directions), persistent=False)
        self.register_buffer("colour_L3", torch.tensor(LED_COLOURS), persistent=False)
        self.register_buffer("azimuth_L", torch.tensor(azimuths), persistent=False)

    def background(self, height: int, width: int, device: torch.device) -> torch.Tensor:
        ys, xs = torch.meshgrid(torch.linspace(-1, 1, height, device=device),
                                torch.linspace(-1, 1, width, device=device), indexing="ij")
        image = torch.full((3, height, width), self.config.background_level, device=device)
        for azimuth, colour in zip(self.azimuth_L.to(device), self.colour_L3.to(device)):
            # Each LED sits just outside the gel edge in its azimuth direction.
            led_x, led_y = 1.3 * torch.cos(azimuth), 1.3 * torch.sin(azimuth)
            glow = torch.exp(-((xs - led_x) ** 2 + (ys - led_y) ** 2) / (2 * 0.6**2))
            image = image + self.config.led_glow * colour[:, None, None] * glow
        image = image * (1 - self.config.vignetting * (xs**2 + ys**2) / 2)
        return image.clamp(0, 1)

    def contact_response(self, height_mm_BHW: torch.Tensor) -> torch.Tensor:
        _, rows, cols = height_mm_BHW.shape
        slope_row, slope_col = surface_slopes(height_mm_BHW, self.pixel_size_mm(rows, cols))
        normal = torch.stack([-slope_col, -slope_row, torch.ones_like(slope_row)], dim=-1)
        normal = normal / normal.norm(dim=-1, keepdim=True)
        light = self.light_L3.to(normal)
        shading_BHWL = (normal @ light.T).clamp_min(0) - light[:, 2]
        response_BHW3 = self.config.response_gain * shading_BHWL @ self.colour_L3.to(normal)
        return response_BHW3.permute(0, 3, 1, 2)


def build_digit(config: DigitConfig, context: BuildContext) -> DigitSensor:
    """Factory for the ``digit`` sensor family."""
    return DigitSensor(config)


@hookimpl
def vqtouch_register_sensor_families(register):
    register("digit", build_digit, DigitConfig,
             description="DIGIT-style three-LED photometric model (not a measured calibration).")

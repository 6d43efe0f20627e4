"""A test sensor far in look from every bundled family, with the same contacts: ``far_mini``.

Load it with ``PYTHONPATH=bench VQTOUCH_PLUGINS=far_sensor_plugin`` (it is a bench plugin, not a
built-in family, so the default families that ``vqtouch adapt`` and ``cluster`` fit stay as they are)::

    PYTHONPATH=bench VQTOUCH_PLUGINS=far_sensor_plugin vqtouch fewshot --run pretrained:tour \\
        --images far_mini --shots 50 --family 0 --out runs/fewshot_far

It stands in for a GelSight Mini-style gel under other lighting, the case where few-shot generation
broke: a smooth teal-to-purple gradient for the no-contact image, and each contact drawn only as
faint bright and dark edges (the slope along one oblique light, no colour-coded normals), so its
frames share almost no pixel statistics with GelSight's or DIGIT's.  The contact geometry is the
shared procedural one, so a condition's paired truth is this sensor's rendering of its own contact.
It models no real sensor; it exists to test adaptation to a large shift in look.
"""

from __future__ import annotations

import math
from typing import Literal

import torch
from pydantic import Field

from vqtouch.core import BuildContext, PluginConfig, hookimpl
from vqtouch.sensors import RenderedSensor, SensorVariant, surface_slopes


class FarMiniConfig(PluginConfig):
    """Options of the ``far_mini`` test sensor."""

    name: Literal["far_mini"] = "far_mini"
    top_colour: tuple[float, float, float] = Field(
        (0.12, 0.55, 0.55), description="RGB of the no-contact image's top edge (teal)."
    )
    bottom_colour: tuple[float, float, float] = Field(
        (0.45, 0.22, 0.58), description="RGB of the no-contact image's bottom edge (purple)."
    )
    light_azimuth_deg: float = Field(
        35.0, ge=-180.0, le=180.0, description="Image azimuth of the one oblique light (0 = +column)."
    )
    edge_gain: float = Field(
        0.35, ge=0.0, le=5.0, description="Brightness change per unit slope along the light: small = faint edges."
    )
    field_of_view_mm: float = Field(15.0, ge=4.0, le=60.0, description="Side of the imaged gel square in mm.")
    gel_blur_mm: float = Field(0.5, ge=0.0, le=2.0, description="Gaussian smoothing of the indentation in mm.")
    variant: SensorVariant = Field(
        default_factory=lambda: SensorVariant(noise_std=0.01), description="Perturbations (default: camera noise)."
    )


class FarMiniSensor(RenderedSensor):
    """A two-colour gradient with contacts as faint directional edges (see the module docstring)."""

    sensor_id = "far_mini"

    def __init__(self, config: FarMiniConfig) -> None:
        super().__init__(config.variant, config.gel_blur_mm)
        self.config = config
        self.field_of_view_mm = config.field_of_view_mm

    def background(self, height: int, width: int, device: torch.device) -> torch.Tensor:
        top = torch.tensor(self.config.top_colour, device=device).view(3, 1, 1)
        bottom = torch.tensor(self.config.bottom_colour, device=device).view(3, 1, 1)
        rows = torch.linspace(0, 1, height, device=device).view(1, height, 1)
        return (top + (bottom - top) * rows).expand(3, height, width).clone()

    def contact_response(self, height_mm_BHW: torch.Tensor) -> torch.Tensor:
        slope_row, slope_col = surface_slopes(height_mm_BHW, self.pixel_size_mm(*height_mm_BHW.shape[-2:]))
        azimuth = math.radians(self.config.light_azimuth_deg)
        along_light = math.cos(azimuth) * slope_col + math.sin(azimuth) * slope_row
        return (self.config.edge_gain * along_light).unsqueeze(1).expand(-1, 3, -1, -1)


def build_far_mini(config: FarMiniConfig, context: BuildContext) -> FarMiniSensor:
    """Factory of the ``far_mini`` test sensor."""
    return FarMiniSensor(config)


@hookimpl
def vqtouch_register_sensor_families(register):
    register(
        "far_mini",
        build_far_mini,
        FarMiniConfig,
        description="Test sensor far in look (teal-to-purple gradient, faint edge contacts); bench plugin.",
    )

"""Example third-party sensor family with printed markers, written against the public API only.

``marker_gel`` is a gel lit by one warm light from above, with a grid of dark ink dots
printed on its surface (as on GelSight-type sensors used for shear and slip).  Pressing an
object tilts the gel: the shading changes (:meth:`MarkerGelSensor.contact_response`) and the
dots slide sideways with the local slope (:meth:`MarkerGelSensor.surface_effects`).  Because
it subclasses :class:`vqtouch.sensors.RenderedSensor`, every :class:`SensorVariant`
perturbation (misalignment, wear, damage, colour, noise) works unchanged and also acts on
the dots.

Only ``vqtouch.core`` and ``vqtouch.sensors`` are imported: the two public modules a sensor
author needs.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

import torch
from pydantic import Field

from vqtouch.core import BuildContext, PluginConfig, hookimpl
from vqtouch.sensors import RenderedSensor, SensorVariant, surface_slopes

UnitFloat = Annotated[float, Field(ge=0.0, le=1.0)]


class MarkerGelConfig(PluginConfig):
    """Options of the ``marker_gel`` sensor family: one-light gel with a printed marker grid."""

    name: Literal["marker_gel"] = "marker_gel"
    field_of_view_mm: float = Field(18.0, ge=4.0, le=60.0, description="Side of the imaged gel square in mm.")
    gel_colour: tuple[UnitFloat, UnitFloat, UnitFloat] = Field(
        (0.78, 0.74, 0.70), description="RGB of the unpressed gel at the image centre, in [0, 1]."
    )
    light_falloff: float = Field(
        0.2,
        ge=0.0,
        le=1.0,
        description="Relative brightness drop from the top edge (near the light) to the bottom edge of the background.",
    )
    light_elevation_deg: float = Field(35.0, ge=5.0, le=85.0, description="Elevation of the light above the gel.")
    light_azimuth_deg: float = Field(
        -90.0, ge=-180.0, le=180.0, description="Azimuth of the light (0: from the right, -90: from the top)."
    )
    response_gain: float = Field(0.8, ge=0.0, le=5.0, description="Strength of the contact shading.")
    gel_blur_mm: float = Field(0.2, ge=0.0, le=2.0, description="Gaussian smoothing of the indentation in mm.")
    marker_pitch_mm: float = Field(
        1.5,
        ge=0.5,
        le=10.0,
        description="Spacing of the marker grid in mm; markers sit at (k + 1/2) pitches "
        "from the top-left corner of the field of view.",
    )
    marker_radius_mm: float = Field(0.25, ge=0.05, le=2.0, description="Radius of one printed marker in mm.")
    marker_colour: tuple[UnitFloat, UnitFloat, UnitFloat] = Field(
        (0.08, 0.08, 0.10), description="RGB of the marker ink, in [0, 1]."
    )
    marker_opacity: float = Field(1.0, ge=0.0, le=1.0, description="Opacity of the ink (0: no markers).")
    marker_shift_mm: float = Field(
        0.4,
        ge=0.0,
        le=5.0,
        description="Sideways shift of a marker in mm where the gel is tilted by 90 "
        "degrees (the shift is this times the sine of the local tilt, away "
        "from the contact's peak).",
    )
    variant: SensorVariant = Field(
        default_factory=SensorVariant, description="Environmental perturbations making this a derived sensor."
    )


class MarkerGelSensor(RenderedSensor):
    """One-light Lambertian gel with a grid of printed markers that move with the surface."""

    sensor_id = "marker_gel"

    def __init__(self, config: MarkerGelConfig) -> None:
        super().__init__(config.variant, config.gel_blur_mm)
        self.config = config
        self.field_of_view_mm = config.field_of_view_mm
        elevation, azimuth = math.radians(config.light_elevation_deg), math.radians(config.light_azimuth_deg)
        # Light direction (x = column, y = row, z = towards the camera).
        light = (math.cos(azimuth) * math.cos(elevation), math.sin(azimuth) * math.cos(elevation), math.sin(elevation))
        self.register_buffer("light_3", torch.tensor(light), persistent=False)
        self.register_buffer("gel_colour_3", torch.tensor(config.gel_colour), persistent=False)
        self.register_buffer("marker_colour_3", torch.tensor(config.marker_colour), persistent=False)

    def background(self, height: int, width: int, device: torch.device) -> torch.Tensor:
        """The gel colour, brighter towards the top edge where the light is."""
        rows = (torch.arange(height, device=device, dtype=torch.float32) + 0.5) / height  # 0 top .. 1 bottom
        brightness = 1.0 + self.config.light_falloff * (0.5 - rows)
        image = self.gel_colour_3.to(device)[:, None, None] * brightness[None, :, None]
        return image.expand(3, height, width).clamp(0.0, 1.0)

    def contact_response(self, height_mm_BHW: torch.Tensor) -> torch.Tensor:
        """Change of Lambertian shading of the tilted gel relative to flat gel, in the gel's colour."""
        _, rows, cols = height_mm_BHW.shape
        slope_row, slope_col = surface_slopes(height_mm_BHW, self.pixel_size_mm(rows, cols))
        normal = torch.stack([-slope_col, -slope_row, torch.ones_like(slope_row)], dim=1)  # (B, 3, H, W)
        normal = normal / normal.norm(dim=1, keepdim=True)
        light = self.light_3.to(normal)
        shading_B1HW = (normal * light[None, :, None, None]).sum(dim=1, keepdim=True).clamp_min(0) - light[2]
        return self.config.response_gain * shading_B1HW * self.gel_colour_3.to(normal)[None, :, None, None]

    def marker_coverage(self, height_mm_BHW: torch.Tensor) -> torch.Tensor:
        """Ink coverage (B, 1, H, W) in [0, 1]: anti-aliased dots, shifted with the local slope."""
        _, rows, cols = height_mm_BHW.shape
        pixel_row, pixel_col = self.pixel_size_mm(rows, cols)
        slope_row, slope_col = surface_slopes(height_mm_BHW, (pixel_row, pixel_col))
        # sin(tilt) along each axis: bounded, so steep walls move a marker by at most marker_shift_mm.
        norm = torch.sqrt(1 + slope_row**2 + slope_col**2)
        shift_row = -self.config.marker_shift_mm * slope_row / norm
        shift_col = -self.config.marker_shift_mm * slope_col / norm
        device = height_mm_BHW.device
        y = (torch.arange(rows, device=device, dtype=torch.float32) + 0.5) * pixel_row
        x = (torch.arange(cols, device=device, dtype=torch.float32) + 0.5) * pixel_col
        # The point of the unpressed gel now seen at each pixel, in pitches from the first marker.
        pitch = self.config.marker_pitch_mm
        rest_row = (y[None, :, None] - shift_row) / pitch - 0.5
        rest_col = (x[None, None, :] - shift_col) / pitch - 0.5
        distance_mm = pitch * torch.sqrt((rest_row - rest_row.round()) ** 2 + (rest_col - rest_col.round()) ** 2)
        coverage = ((self.config.marker_radius_mm - distance_mm) / min(pixel_row, pixel_col) + 0.5).clamp(0.0, 1.0)
        return coverage.unsqueeze(1)

    def surface_effects(self, images_B3HW: torch.Tensor, height_mm_BHW: torch.Tensor) -> torch.Tensor:
        """Paint the marker ink over the shaded gel (before the variant, so it is perturbed too)."""
        ink = self.config.marker_opacity * self.marker_coverage(height_mm_BHW)
        return images_B3HW * (1 - ink) + ink * self.marker_colour_3.to(images_B3HW)[None, :, None, None]


def build_marker_gel(config: MarkerGelConfig, context: BuildContext) -> MarkerGelSensor:
    """Factory for the ``marker_gel`` sensor family."""
    return MarkerGelSensor(config)


@hookimpl
def vqtouch_register_sensor_families(register):
    register(
        "marker_gel",
        build_marker_gel,
        MarkerGelConfig,
        description="Example: one-light gel with printed markers that move with the surface.",
    )

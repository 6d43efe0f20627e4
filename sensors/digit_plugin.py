"""The digit family's plugin: its options and registration
(the renderer, in digit.py, is imported when built)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from vqtouch.core import PluginConfig, hookimpl

from .variant_options import SensorVariant

#: How to get DIGIT's published design when it is missing (named in the warning).
TACTO_INSTALL = "pip install --no-deps tacto==0.0.3"


class DigitConfig(PluginConfig):
    """Options of the ``digit`` sensor family (photometric model).

    Options left at None take their value from ``design``; the module docstring says which
    values are published, which assumed.
    """

    name: Literal["digit"] = "digit"
    design: Literal["tacto", "builtin"] = Field(
        "tacto",
        description="Source of the geometry, light and noise defaults: 'tacto' reads DIGIT's published "
        f"design from tacto's config_digit.yml ({TACTO_INSTALL}; without it: a warning and "
        "the built-in values), 'builtin' uses vqtouch's earlier hand-set values.",
    )
    field_of_view_mm: float | None = Field(
        None,
        ge=4.0,
        le=60.0,
        description="Side of the imaged gel square in mm; None: the design's "
        "(tacto: 20, the gel's width; builtin: 16).",
    )
    led_elevation_deg: float | None = Field(
        None,
        ge=5.0,
        le=85.0,
        description="Elevation of the three LEDs above the gel; None: the design's "
        "(tacto: 40.4, from the light ring's radius and distance; builtin: 25).",
    )
    led_azimuth_deg: float | None = Field(
        None,
        ge=-180.0,
        le=180.0,
        description="Image azimuth of the red LED (0 = +column, 90 = +row, i.e. down); green and blue follow at "
        "+120 and +240. None: the design's (tacto: -150, -30, 90; builtin: 90, 210, 330).",
    )
    camera_noise_std: float | None = Field(
        None,
        ge=0.0,
        le=0.3,
        description="Std of the camera's Gaussian pixel noise on [0, 1], drawn from the render "
        "generator after the variant; None: the design's (tacto: 7/255; "
        "builtin: 0).",
    )
    response_gain: float = Field(0.9, ge=0.0, le=5.0, description="Strength of the contact shading (assumed).")
    background_level: float = Field(0.42, ge=0.0, le=1.0, description="Base intensity of the unlit gel (assumed).")
    led_glow: float = Field(
        0.25, ge=0.0, le=1.0, description="Brightness of each LED's glow at its gel edge (assumed)."
    )
    vignetting: float = Field(0.25, ge=0.0, le=1.0, description="Darkening at the image corners (assumed).")
    gel_blur_mm: float = Field(
        0.25, ge=0.0, le=2.0, description="Gaussian smoothing of the indentation in mm (assumed)."
    )
    variant: SensorVariant = Field(
        default_factory=SensorVariant, description="Environmental perturbations making this a derived sensor."
    )


@hookimpl
def vqtouch_register_sensor_families(register):
    register(
        "digit",
        "vqtouch.sensors.digit:build_digit",
        DigitConfig,
        description="DIGIT three-LED photometric model: geometry, light colours and camera noise from "
        "DIGIT's published design (tacto's config_digit.yml); shading strength and background "
        "assumed.",
    )

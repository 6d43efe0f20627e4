"""The GelSight families' plugin: their options and registration
(the renderer, in gelsight.py, is imported when built)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from vqtouch.core import PluginConfig, hookimpl

from .variant_options import SensorVariant


class GelSightConfig(PluginConfig):
    """Options of the ``gelsight`` sensor family (real taxim calibration)."""

    name: Literal["gelsight"] = "gelsight"
    view: Literal["center_square", "full"] = Field(
        "center_square",
        description="Imaged area: the centred square of the 640x480 frame, or the full frame "
        "(height maps must then be 3:4).",
    )
    gel_blur_mm: float = Field(
        0.2,
        ge=0.0,
        le=2.0,
        description="Gaussian smoothing of the indentation (elastic spread), in mm; the "
        "default fits taxim's real ball presses best (see sensors/fidelity.py).",
    )
    zero_slope_offset: Literal["keep", "remove"] = Field(
        "keep",
        description="The table's response at zero slope: 'keep' it inside the contact (it carries signal "
        "for GelSight), or 'remove' it so flat gel equals the real frame (a fitting bias for "
        "the Mini). Defaults are the better choice on taxim's real presses.",
    )
    variant: SensorVariant = Field(
        default_factory=SensorVariant, description="Environmental perturbations making this a derived sensor."
    )


class GelSightMiniConfig(GelSightConfig):
    """Options of the ``gelsight_mini`` sensor family (real taxim calibration)."""

    name: Literal["gelsight_mini"] = "gelsight_mini"
    gel_blur_mm: float = Field(
        0.5,
        ge=0.0,
        le=2.0,
        description="Gaussian smoothing of the indentation in mm (the Mini's thicker gel "
        "spreads more); fitted on taxim's real ball presses.",
    )
    zero_slope_offset: Literal["keep", "remove"] = Field(
        "remove",
        description="The table's response at zero slope (about +0.04/+0.05/+0.11 RGB for the Mini, a "
        "fitting bias): 'remove' keeps flat gel equal to the real frame.",
    )


@hookimpl
def vqtouch_register_sensor_families(register):
    register(
        "gelsight",
        "vqtouch.sensors.gelsight:build_gelsight",
        GelSightConfig,
        description="GelSight, rendered from taxim's real measured calibration.",
    )
    register(
        "gelsight_mini",
        "vqtouch.sensors.gelsight:build_gelsight_mini",
        GelSightMiniConfig,
        description="GelSight Mini, rendered from taxim's real measured calibration.",
    )

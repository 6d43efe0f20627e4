"""A sensor variant's options (:class:`SensorVariant`; applying one is in :mod:`.variants`): light, so the
sensor families' plugin modules import no torch."""

from __future__ import annotations

from pydantic import Field

from vqtouch.core.plugin_config import StrictModel


class SensorVariant(StrictModel):
    """Perturbations of one sensor relative to its family's calibration (defaults: none)."""

    illumination_shift: float = Field(
        0.0, ge=-0.5, le=0.5, description="Brightness offset added to every channel (LED intensity drift)."
    )
    colour_gain: tuple[float, float, float] = Field(
        (1.0, 1.0, 1.0), description="Per-channel RGB gain (LED colour or camera white-balance change)."
    )
    background_drift: float = Field(
        0.0,
        ge=0.0,
        le=0.3,
        description="Amplitude of a smooth colour field added to the no-contact background (calibration drift).",
    )
    response_scale: float = Field(
        1.0,
        ge=0.0,
        le=3.0,
        description="Scale of the contact response relative to the calibration table (gel stiffness or table drift).",
    )
    wear_blur: float = Field(
        0.0, ge=0.0, le=0.1, description="Gaussian blur sigma as a fraction of the image side (worn, hazy gel)."
    )
    damage_spots: int = Field(0, ge=0, le=64, description="Number of damaged gel spots (darkened blotches).")
    damage_strength: float = Field(0.5, ge=0.0, le=1.0, description="How dark a damaged spot gets at its centre.")
    noise_std: float = Field(0.0, ge=0.0, le=0.3, description="Std of per-image Gaussian pixel noise (camera noise).")
    shift: tuple[float, float] = Field((0.0, 0.0), description="Misalignment (x, y) as a fraction of the image side.")
    rotation_deg: float = Field(0.0, ge=-30.0, le=30.0, description="Misalignment rotation in degrees.")
    seed: int = Field(0, ge=0, le=2**31 - 1, description="Seed fixing this variant's drift pattern and damage.")

    def is_identity(self) -> bool:
        """True when the variant changes nothing."""
        return self == SensorVariant()

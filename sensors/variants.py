"""Sensor variants: the environmental factors that make two sensors of a family differ.

A variant is configuration (a family plus a :class:`SensorVariant`), so an unseen
"derivative version" of a sensor can be made on demand, e.g.::

    {"name": "gelsight", "variant": {"colour_gain": [1.1, 0.95, 0.9], "wear_blur": 0.01, "seed": 3}}

All random fields of a variant (background drift pattern, damaged spots) are fixed by its
``seed``, so a variant behaves like one physical sensor across images; only ``noise_std``
differs per image (drawn from the caller's generator).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from .variant_options import SensorVariant


def environment_variant(seed: int, strength: float = 1.0) -> SensorVariant:
    """A random derived sensor drawn from every environmental factor at once, fixed by ``seed``.

    Each factor is drawn uniformly within a range typical of one physical sensor drifting or
    ageing relative to its family (``strength`` scales every range: 0 gives the family itself):
    illumination shift +-0.05, colour gain 1 +- 0.1 per channel, background drift up to 0.06,
    response scale 1 +- 0.15, wear blur up to 1% of the side, up to 2 damaged spots, camera noise
    up to 0.015, misalignment up to 2% of the side and 2 degrees.  The ranges are assumptions
    (no measured spread across individual sensors ships), chosen so a variant stays visibly of
    its family.  Used for family-recovery experiments and the ``cluster`` stage's default sensors.
    """
    if not 0 <= strength <= 3:
        raise ValueError(f"strength must lie in [0, 3], got {strength}")
    generator = torch.Generator().manual_seed(1_000_003 + seed)

    def uniform(low: float, high: float) -> float:
        return float(low + (high - low) * torch.rand((), generator=generator, dtype=torch.float64))

    spots = int(torch.randint(0, 3, (), generator=generator)) if strength > 0 else 0
    return SensorVariant(
        illumination_shift=strength * uniform(-0.05, 0.05),
        colour_gain=tuple(1 + strength * uniform(-0.1, 0.1) for _ in range(3)),
        background_drift=strength * uniform(0.0, 0.06),
        response_scale=1 + strength * uniform(-0.15, 0.15),
        wear_blur=strength * uniform(0.0, 0.01),
        damage_spots=spots,
        noise_std=strength * uniform(0.0, 0.015),
        shift=(strength * uniform(-0.02, 0.02), strength * uniform(-0.02, 0.02)),
        rotation_deg=strength * uniform(-2.0, 2.0),
        seed=seed,
    )


def _variant_generator(variant: SensorVariant, salt: int) -> torch.Generator:
    return torch.Generator().manual_seed(variant.seed * 7919 + salt)


def _smooth_field(generator: torch.Generator, channels: int, height: int, width: int) -> torch.Tensor:
    """A smooth random field in [-1, 1], resolution-independent (drawn on a coarse 4x4 grid)."""
    coarse = torch.rand(1, channels, 4, 4, generator=generator) * 2 - 1
    return F.interpolate(coarse, size=(height, width), mode="bicubic", align_corners=True)[0].clamp(-1, 1)


def drifted_background(background_3HW: torch.Tensor, variant: SensorVariant) -> torch.Tensor:
    """The family's no-contact background with this variant's calibration drift added."""
    if variant.background_drift == 0:
        return background_3HW
    field = _smooth_field(_variant_generator(variant, 1), 3, *background_3HW.shape[-2:])
    return background_3HW + variant.background_drift * field.to(background_3HW)


def gaussian_blur(images_BCHW: torch.Tensor, sigma_px: float) -> torch.Tensor:
    """Separable Gaussian blur with replicated borders (identity for sigma <= 0)."""
    if sigma_px <= 0:
        return images_BCHW
    radius = max(1, math.ceil(3 * sigma_px))
    coords = torch.arange(-radius, radius + 1, dtype=images_BCHW.dtype, device=images_BCHW.device)
    kernel = torch.exp(-(coords**2) / (2 * sigma_px**2))
    kernel = kernel / kernel.sum()
    channels = images_BCHW.shape[1]
    padded = F.pad(images_BCHW, (radius, radius, 0, 0), mode="replicate")
    out = F.conv2d(padded, kernel.view(1, 1, 1, -1).expand(channels, 1, 1, -1), groups=channels)
    padded = F.pad(out, (0, 0, radius, radius), mode="replicate")
    return F.conv2d(padded, kernel.view(1, 1, -1, 1).expand(channels, 1, -1, 1), groups=channels)


def _damage_mask(variant: SensorVariant, height: int, width: int) -> torch.Tensor:
    """(1, H, W) multiplicative darkening from the variant's damaged spots."""
    generator = _variant_generator(variant, 2)
    ys, xs = torch.meshgrid(torch.linspace(0, 1, height), torch.linspace(0, 1, width), indexing="ij")
    mask = torch.ones(height, width)
    for _ in range(variant.damage_spots):
        cx, cy = torch.rand(2, generator=generator).tolist()
        radius = 0.02 + 0.06 * float(torch.rand(1, generator=generator))
        spot = torch.exp(-((xs - cx) ** 2 + (ys - cy) ** 2) / (2 * radius**2))
        mask = mask * (1 - variant.damage_strength * spot)
    return mask.unsqueeze(0)


def apply_variant(
    images_B3HW: torch.Tensor, variant: SensorVariant, generator: torch.Generator | None = None
) -> torch.Tensor:
    """Apply the variant's image-space effects: misalignment, wear, damage, colour, noise."""
    if variant.is_identity():
        return images_B3HW
    batch, _, height, width = images_B3HW.shape
    images = images_B3HW
    if variant.shift != (0.0, 0.0) or variant.rotation_deg != 0:
        angle = math.radians(variant.rotation_deg)
        theta = torch.tensor(
            [
                [math.cos(angle), -math.sin(angle), 2 * variant.shift[0]],
                [math.sin(angle), math.cos(angle), 2 * variant.shift[1]],
            ],
            dtype=images.dtype,
        )
        grid = F.affine_grid(theta.expand(batch, 2, 3).to(images.device), list(images.shape), align_corners=False)
        images = F.grid_sample(images, grid, mode="bilinear", padding_mode="border", align_corners=False)
    images = gaussian_blur(images, variant.wear_blur * max(height, width))
    if variant.damage_spots:
        images = images * _damage_mask(variant, height, width).to(images)
    gain = torch.tensor(variant.colour_gain, dtype=images.dtype, device=images.device).view(1, 3, 1, 1)
    images = images * gain + variant.illumination_shift
    if variant.noise_std:
        noise = (
            torch.randn(images.shape, generator=generator, dtype=images.dtype)
            if generator is not None
            else torch.randn_like(images)
        )
        images = images + variant.noise_std * noise.to(images.device)
    return images

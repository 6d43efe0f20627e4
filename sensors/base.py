"""What every rendered sensor family shares: a no-contact background plus a contact
response computed from surface slopes, the sensor's own surface effects, then the
variant's perturbations.

Third-party families subclass :class:`RenderedSensor` through the public API
(``from vqtouch.sensors import RenderedSensor, SensorVariant, ...``), never by importing
this module directly.
"""

from __future__ import annotations

import abc

import torch

from vqtouch.core import SensorFamily

from .variants import SensorVariant, apply_variant, drifted_background, gaussian_blur


def surface_slopes(height_mm_BHW: torch.Tensor, pixel_mm: tuple[float, float]) -> tuple[torch.Tensor, torch.Tensor]:
    """Central-difference slopes of height maps (B, H, W): (d height / d row, d height / d column).

    ``pixel_mm`` is the (row, column) size of one pixel in mm (see
    :meth:`RenderedSensor.pixel_size_mm`), so the slopes are dimensionless (mm per mm).
    """
    slope_row, slope_col = torch.gradient(height_mm_BHW, spacing=pixel_mm, dim=(1, 2))
    return slope_row, slope_col


def check_height_map(height_mm_BHW: torch.Tensor) -> torch.Tensor:
    """Validate a batch of height maps (B, H, W) in mm and return it as float32.

    Raises ValueError for a wrong shape, maps smaller than 2x2, NaN/Inf, or negative depths.
    """
    if not isinstance(height_mm_BHW, torch.Tensor) or height_mm_BHW.ndim != 3:
        shape = tuple(height_mm_BHW.shape) if isinstance(height_mm_BHW, torch.Tensor) else type(height_mm_BHW)
        raise ValueError(f"sensor render expects height maps of shape (B, H, W) in mm, got {shape}")
    if min(height_mm_BHW.shape[-2:]) < 2:
        raise ValueError(f"height maps must be at least 2x2 pixels, got {tuple(height_mm_BHW.shape[-2:])}")
    height = height_mm_BHW.float()
    if not torch.isfinite(height).all():
        raise ValueError("height map contains NaN or Inf")
    if (height < 0).any():
        raise ValueError(f"height map must be >= 0 mm (indentation depth); min is {float(height.min()):.4g}")
    return height


class RenderedSensor(SensorFamily):
    """A sensor rendered as background + contact response + surface effects, then perturbed by its variant.

    :meth:`render` runs, for height maps (B, H, W) in mm over the field of view:

    1. :func:`check_height_map`, then a Gaussian smoothing of the indentation by
       ``gel_blur_mm`` (the elastomer spreads a point load);
    2. :meth:`contact_response` of the smoothed indentation, scaled by the variant's
       ``response_scale``, added to :meth:`background` (with the variant's calibration drift);
    3. :meth:`surface_effects`: what the sensor's own gel adds on top of the shading (printed
       markers, gel texture, ...); identity by default;
    4. :func:`apply_variant`: the variant's image-space effects (misalignment, wear, damage,
       colour, noise), which therefore also act on the surface effects; then a clamp to [0, 1].

    Subclasses provide :meth:`background` and :meth:`contact_response` and may override
    :meth:`surface_effects`; the flow, input checks, gel smoothing and variant effects live
    here once.  Like every :class:`~vqtouch.core.SensorFamily`, a subclass sets
    ``field_of_view_mm`` (side of the imaged square in mm, as a class attribute or in
    ``__init__``; :meth:`pixel_size_mm` derives from it) and may set ``sensor_id``.  A family
    with real captured frames overrides :meth:`reference_frames` (the default: None).
    """

    def __init__(self, variant: SensorVariant, gel_blur_mm: float) -> None:
        super().__init__()
        self.variant = variant
        self.gel_blur_mm = gel_blur_mm

    def pixel_size_mm(self, height: int, width: int) -> tuple[float, float]:
        """Size of one output pixel (row, column) in mm for an H x W render of the imaged area."""
        rows_mm, cols_mm = self.imaged_extent_mm(height, width)
        return rows_mm / height, cols_mm / width

    @abc.abstractmethod
    def background(self, height: int, width: int, device: torch.device) -> torch.Tensor:
        """The no-contact image (3, H, W) in [0, 1]."""

    @abc.abstractmethod
    def contact_response(self, height_mm_BHW: torch.Tensor) -> torch.Tensor:
        """Intensity change (B, 3, H, W) caused by the indentation, in [0, 1] units."""

    def surface_effects(self, images_B3HW: torch.Tensor, height_mm_BHW: torch.Tensor) -> torch.Tensor:
        """The sensor's own marks on the shaded gel: printed markers, gel texture, coating flaws.

        Called by :meth:`render` after background + contact response and before the variant,
        with the shaded images (B, 3, H, W) (not yet clamped) and the gel-smoothed indentation
        (B, H, W) in mm that produced them; returns images of the same shape.  Because the
        variant comes after, its misalignment, blur, damage, colour and noise act on these
        effects too.  The default returns ``images_B3HW`` unchanged.
        """
        return images_B3HW

    def render(self, height_mm_BHW: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """Height maps (B, H, W) in mm over the field of view -> RGB tactile images (B, 3, H, W) in [0, 1]."""
        height = check_height_map(height_mm_BHW)
        _, rows, cols = height.shape
        if self.gel_blur_mm > 0:
            # The elastomer spreads a point load: smooth the indentation before shading it.
            sigma_px = self.gel_blur_mm / min(self.pixel_size_mm(rows, cols))
            height = gaussian_blur(height.unsqueeze(1), sigma_px).squeeze(1)
        response = self.contact_response(height) * self.variant.response_scale
        background = drifted_background(self.background(rows, cols, height.device), self.variant)
        images = self.surface_effects(background.unsqueeze(0) + response, height)
        images = apply_variant(images, self.variant, generator)
        return images.clamp(0.0, 1.0)

"""Sim-vs-real check: render taxim's real ball presses and compare with the real frames.

``taxim``'s ``dataPack.npz`` holds real frames of a ball pressed into each sensor, with the
contact centre (column, row) and contact radius in full-resolution pixels.  We rebuild each
press as a spherical cap, render it with our sensor family, and score SSIM and PSNR on a
square crop around every contact, next to the same scores for the no-contact background
alone (what a renderer that draws nothing would get).  Whole frames are mostly background,
so whole-frame scores say little; the crops are what matter.

Note: the calibration tables were fitted on these same frames, so this is an in-sample
check of the renderer, not of generalisation.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from vqtouch.core import PluginHost
from .gelsight import load_taxim_calibration

#: Ball radius (mm) of the real presses: 2.0 mm as in Taxim's sensor parameters.  The Mini's
#: data do not record it; 2.0 mm is also among the best for it (radii 1-4 mm were tried).
BALL_RADIUS_MM = {"gelsight": 2.0, "gelsight_mini": 2.0}


@dataclass
class FidelityResult:
    """Scores of one sensor family against its real frames."""

    sensor: str
    frames: int
    crop_px: int
    resolution: tuple[int, int]
    ssim: float
    psnr: float
    background_ssim: float
    background_psnr: float
    real_crops: torch.Tensor
    rendered_crops: torch.Tensor

    def summary(self) -> dict[str, Any]:
        """The numbers, JSON-ready."""
        return {
            "sensor": self.sensor,
            "frames": self.frames,
            "crop_px": self.crop_px,
            "resolution": list(self.resolution),
            "ssim": round(self.ssim, 4),
            "psnr_db": round(self.psnr, 2),
            "background_only_ssim": round(self.background_ssim, 4),
            "background_only_psnr_db": round(self.background_psnr, 2),
        }


def ball_press_heights(
    centres_xy: np.ndarray,
    contact_radii: np.ndarray,
    ball_radius_mm: float,
    pixel_mm: float,
    native_size: tuple[int, int],
    size: tuple[int, int],
) -> torch.Tensor:
    """Spherical-cap height maps (B, H, W) in mm for presses given in full-resolution pixels."""
    rows_native, cols_native = native_size
    rows = (torch.arange(size[0], dtype=torch.float64) + 0.5) * rows_native / size[0] - 0.5
    cols = (torch.arange(size[1], dtype=torch.float64) + 0.5) * cols_native / size[1] - 0.5
    y, x = torch.meshgrid(rows, cols, indexing="ij")
    heights = []
    for (cx, cy), radius_px in zip(centres_xy.astype(np.float64), contact_radii.astype(np.float64)):
        r_sq_mm = ((x - cx) ** 2 + (y - cy) ** 2) * pixel_mm**2
        contact_mm = min(radius_px * pixel_mm, ball_radius_mm * 0.999)
        cap = (ball_radius_mm**2 - r_sq_mm).clamp_min(0).sqrt() - (ball_radius_mm**2 - contact_mm**2) ** 0.5
        heights.append(cap.clamp_min(0))
    return torch.stack(heights).float()


def _crops(images: torch.Tensor, centres_xy: np.ndarray, native_size: tuple[int, int], crop: int) -> torch.Tensor:
    _, _, rows, cols = images.shape
    out = []
    for index, (cx, cy) in enumerate(centres_xy.astype(np.float64)):
        top = int(np.clip(round(cy * rows / native_size[0]) - crop // 2, 0, rows - crop))
        left = int(np.clip(round(cx * cols / native_size[1]) - crop // 2, 0, cols - crop))
        out.append(images[index, :, top : top + crop, left : left + crop])
    return torch.stack(out)


def evaluate_fidelity(
    sensor_name: str,
    host: PluginHost,
    resolution: tuple[int, int] = (240, 320),
    crop_px: int = 64,
    ball_radius_mm: float | None = None,
    sensor_options: dict[str, Any] | None = None,
) -> FidelityResult:
    """Render every real press of ``sensor_name`` and score it against the real frames."""
    calibration = load_taxim_calibration(sensor_name)
    sensor = host.build("sensor_family", {"name": sensor_name, **(sensor_options or {}), "view": "full"})
    # The real presses over the whole frame (the same reader as the renderer's background).
    real = sensor.reference_frames(*resolution)
    with np.load(calibration.folder / "dataPack.npz", allow_pickle=False) as pack:
        centres = pack["touch_center"].astype(np.float64)  # (column, row); uint16 in the Mini's file
        radii = pack["touch_radius"].astype(np.float64)
    radius = BALL_RADIUS_MM[sensor_name] if ball_radius_mm is None else ball_radius_mm
    heights = ball_press_heights(centres, radii, radius, calibration.pixel_mm, calibration.native_size, resolution)
    with torch.no_grad():
        rendered = sensor.render(heights)
    background = sensor.background(*resolution, torch.device("cpu")).expand_as(real)
    real_crops = _crops(real, centres, calibration.native_size, crop_px)
    rendered_crops = _crops(rendered, centres, calibration.native_size, crop_px)
    background_crops = _crops(background, centres, calibration.native_size, crop_px)
    scores = {}
    for metric_name in ("ssim", "psnr"):
        metric = host.build("metric", metric_name)
        for label, crops in (("render", rendered_crops), ("background", background_crops)):
            metric.reset()
            metric.update(crops, real_crops)
            scores[(metric_name, label)] = metric.compute()
    return FidelityResult(
        sensor_name,
        len(real),
        crop_px,
        resolution,
        scores[("ssim", "render")],
        scores[("psnr", "render")],
        scores[("ssim", "background")],
        scores[("psnr", "background")],
        real_crops,
        rendered_crops,
    )

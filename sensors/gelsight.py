"""GelSight and GelSight Mini, rendered from their real measured calibrations.

The calibration files ship in the PyPI package ``taxim`` (``taxim/calib/gelsight`` and
``gelsight_mini``): a polynomial colour table over surface-gradient bins and a real
no-contact frame.  Only the data files are used; the renderer is written here.

Model (per RGB channel c, for an output pixel at full-resolution position (x=column, y=row)):
``I_c = B_c + sum_m P_c[i, j, m] * psi_m(x, y)``, ``psi = (x^2, y^2, xy, x, y, 1)``, where the bin
``i`` quantises the slope angle ``theta = atan|grad z|`` over [0, pi/2) and ``j`` the slope direction
``phi = atan2(dz/drow, dz/dcol)`` over (-pi, pi], each into ``bins`` steps.  The contact height map
``z`` is the shape pressed into the gel (a bump towards the camera), as in the calibration.

taxim's ``dataPack.npz`` also holds real frames captured with each sensor (a no-contact
frame ``f0`` and ball presses ``imgs``).  :func:`taxim_frames` is the one reader of them;
the background above, :meth:`GelSightSensor.reference_frames` and the sim-vs-real check in
:mod:`vqtouch.sensors.fidelity` all go through it.
"""

from __future__ import annotations

import functools
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
import torch.nn.functional as F

from vqtouch.core import BuildContext, PluginError

from .base import RenderedSensor, surface_slopes
from .gelsight_plugin import GelSightConfig, GelSightMiniConfig  # noqa: F401 - re-exported
from .variants import SensorVariant

TAXIM_FOLDERS = {"gelsight": "CALIB_GELSIGHT", "gelsight_mini": "CALIB_GELSIGHT_MINI"}


@dataclass(frozen=True)
class TaximCalibration:
    """One sensor's calibration as read from taxim's files (RGB order, intensities in [0, 1])."""

    sensor: str
    background_3HW: torch.Tensor
    table_NN36: np.ndarray
    pixel_mm: float
    bins: int
    folder: Path

    @property
    def native_size(self) -> tuple[int, int]:
        """(rows, columns) of the calibration frames."""
        return self.background_3HW.shape[-2], self.background_3HW.shape[-1]


def calibration_folder(sensor: str) -> Path:
    """Folder of taxim's calibration files for ``sensor`` (fails clearly without taxim)."""
    try:
        import taxim
    except ImportError as exc:
        raise PluginError(
            f"sensor family {sensor!r} reads its calibration from the taxim package ({exc}); pip install taxim"
        ) from None
    return Path(getattr(taxim, TAXIM_FOLDERS[sensor]))


def taxim_frames(sensor: str, key: Literal["imgs", "f0"] = "imgs") -> torch.Tensor:
    """taxim's real frames of ``sensor`` (``"gelsight"`` or ``"gelsight_mini"``) as float32 RGB
    (N, 3, H, W) in [0, 1] at native resolution (480 x 640), uncropped.

    ``key="imgs"``: the real ball presses (N = 48 for GelSight, 24 for the Mini);
    ``key="f0"``: the no-contact frame (N = 1).  This is the only place taxim's frames are
    decoded (OpenCV's BGR order to RGB, uint8 / 255).  Nothing is cached: the presses take
    about 180 MB as floats.
    """
    with np.load(calibration_folder(sensor) / "dataPack.npz", allow_pickle=False) as pack:
        frames_NHW3 = pack[key]
    if frames_NHW3.ndim == 3:
        frames_NHW3 = frames_NHW3[None]
    # Frames were captured by OpenCV in BGR order.  The channel axis is moved by a view
    # (channels-last memory) exactly as the three readers this one replaced did.
    rgb_NHW3 = torch.from_numpy(np.ascontiguousarray(frames_NHW3[..., ::-1]))
    return rgb_NHW3.permute(0, 3, 1, 2).float() / 255.0


@functools.lru_cache(maxsize=4)
def load_taxim_calibration(sensor: str) -> TaximCalibration:
    """Read and convert one sensor's calibration (cached per process)."""
    folder = calibration_folder(sensor)
    params = json.loads((folder / "params.json").read_text())["sensor"]
    background_3HW = taxim_frames(sensor, "f0")[0]
    with np.load(folder / "polycalib.npz", allow_pickle=False) as poly:
        # taxim's grad_r table holds BGR channel 0 (blue) and grad_b holds red: stack as RGB.
        table = np.stack([poly["grad_b"], poly["grad_g"], poly["grad_r"]], axis=2).astype(np.float32) / 255.0
        bins = int(poly["bins"])
    return TaximCalibration(sensor, background_3HW, table, float(params["pixmm"]), bins, folder)


class GelSightSensor(RenderedSensor):
    """Polynomial-table renderer for a calibrated GelSight-type sensor.

    The imaged area (``view``) is the centred square of taxim's 480 x 640 frames
    (``"center_square"``) or the whole frame (``"full"``; height maps must then be 3:4);
    ``field_of_view_mm`` is its height in mm (from the calibration's pixel size) and
    ``sensor_id`` is the taxim sensor (``"gelsight"`` or ``"gelsight_mini"``).  The real
    frames taxim captured with the sensor are its :meth:`reference_frames`, over the same
    imaged area.
    """

    def __init__(
        self,
        calibration: TaximCalibration,
        sensor_id: str,
        view: str,
        gel_blur_mm: float,
        variant: SensorVariant,
        zero_slope_offset: str = "keep",
    ) -> None:
        super().__init__(variant, gel_blur_mm)
        self.sensor_id = sensor_id
        self.taxim_sensor = calibration.sensor
        self.view = view
        rows, cols = calibration.native_size
        self.crop_cols = (cols - rows) // 2 if view == "center_square" else 0
        self.crop_size = (rows, rows if view == "center_square" else cols)
        self.native_pixel_mm = calibration.pixel_mm
        self.field_of_view_mm = self.crop_size[0] * calibration.pixel_mm
        self.bins = calibration.bins
        # Calibration data are not trained: non-persistent, so checkpoints stay small and
        # always use the installed calibration.  (A clone: the calibration is cached.)
        self.register_buffer("background_3HW", calibration.background_3HW.clone(), persistent=False)
        table_NN36 = torch.from_numpy(calibration.table_NN36.copy())
        if zero_slope_offset == "remove":
            # Response relative to the zero-slope bin: flat gel equals the real frame, and gently
            # sloped gel around a smoothed indentation gets no spurious halo.
            table_NN36 = table_NN36 - table_NN36[0].mean(dim=0)
        self.register_buffer("table_K36", table_NN36.reshape(self.bins * self.bins, 3, 6), persistent=False)
        self._background_cache: dict[tuple[int, int, str], torch.Tensor] = {}

    def imaged_extent_mm(self, height: int, width: int) -> tuple[float, float]:
        """The imaged crop of the real frame (``view``), in mm, whatever the render's size."""
        return self.native_pixel_mm * self.crop_size[0], self.native_pixel_mm * self.crop_size[1]

    def _imaged_area(self, frames_N3HW: torch.Tensor, height: int, width: int) -> torch.Tensor:
        """Native-resolution frames cropped to the imaged area (``view``) and resized to height x width."""
        cropped = frames_N3HW[:, :, :, self.crop_cols : self.crop_cols + self.crop_size[1]]
        return F.interpolate(cropped, size=(height, width), mode="bilinear", antialias=True, align_corners=False)

    def background(self, height: int, width: int, device: torch.device) -> torch.Tensor:
        key = (height, width, str(device))
        if key not in self._background_cache:
            resized = self._imaged_area(self.background_3HW.unsqueeze(0), height, width)[0]
            self._background_cache[key] = resized.to(device)
        return self._background_cache[key]

    def reference_frames(self, height: int, width: int) -> torch.Tensor:
        """taxim's real ball presses with this sensor, (N, 3, height, width) RGB in [0, 1].

        Cropped to the imaged area like :meth:`render` (the centred square for
        ``view="center_square"``, the whole frame for ``"full"``) and resized with antialiased
        bilinear interpolation; no variant is applied.  Read from disk on every call (N = 48
        for GelSight, 24 for the Mini); returned on the device of the sensor's buffers.
        """
        frames = self._imaged_area(taxim_frames(self.taxim_sensor), height, width)
        return frames.to(self.background_3HW.device)

    def _native_coordinates(self, height: int, width: int, device: torch.device) -> torch.Tensor:
        """psi = (x^2, y^2, xy, x, y, 1) at each output pixel's centre in full-frame pixels, (H, W, 6)."""
        rows = (torch.arange(height, device=device) + 0.5) * self.crop_size[0] / height - 0.5
        cols = (torch.arange(width, device=device) + 0.5) * self.crop_size[1] / width - 0.5 + self.crop_cols
        y, x = torch.meshgrid(rows, cols, indexing="ij")
        return torch.stack([x * x, y * y, x * y, x, y, torch.ones_like(x)], dim=-1)

    def contact_response(self, height_mm_BHW: torch.Tensor) -> torch.Tensor:
        _, rows, cols = height_mm_BHW.shape
        slope_row, slope_col = surface_slopes(height_mm_BHW, self.pixel_size_mm(rows, cols))
        magnitude = torch.sqrt(slope_row**2 + slope_col**2)
        theta = torch.atan(magnitude)
        phi = torch.atan2(slope_row, slope_col)
        scale = self.bins - 1
        theta_bin = (theta * scale / (math.pi / 2)).floor().long().clamp(0, scale)
        phi_bin = ((phi + math.pi) * scale / (2 * math.pi)).floor().long().clamp(0, scale)
        coefficients_BHW36 = self.table_K36[theta_bin * self.bins + phi_bin]
        psi_HW6 = self._native_coordinates(rows, cols, height_mm_BHW.device)
        response_BHW3 = torch.einsum("bhwcm,hwm->bhwc", coefficients_BHW36, psi_HW6)
        # Flat pixels show the background: no slope direction (atan2(0, 0) would pick one bin).
        response_BHW3 = response_BHW3 * (magnitude > 1e-6).unsqueeze(-1)
        return response_BHW3.permute(0, 3, 1, 2)


def _build(sensor: str):
    def build(config: GelSightConfig, context: BuildContext) -> GelSightSensor:
        return GelSightSensor(
            load_taxim_calibration(sensor),
            sensor,
            config.view,
            config.gel_blur_mm,
            config.variant,
            config.zero_slope_offset,
        )

    build.__doc__ = f"Factory for the {sensor!r} sensor family."
    return build


#: The two families' factories (the plugin module names them by reference).
build_gelsight = _build("gelsight")
build_gelsight_mini = _build("gelsight_mini")

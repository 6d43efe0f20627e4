"""DIGIT sensor: a photometric renderer whose geometry, lights and camera noise follow DIGIT's
published design.

DIGIT's design (Lambeta et al., 2020) is published, as its simulator TACTO models it (Wang et
al., 2022), in the data file ``tacto/config_digit.yml`` of the PyPI package ``tacto`` (0.0.3, MIT):
camera pose and vertical field of view, gel size and position, three point lights in polar form
with their colours, and the camera's pixel noise.  vqtouch reads only that file
(``pip install --no-deps tacto==0.0.3``); the package itself needs pyrender and OpenGL and is never
imported.  Without the file the family warns once and uses its built-in values instead (the same as
``design="builtin"``).

Three coloured LEDs (red, green, blue) light the gel from the sides.  The camera sees:

- a background: a base level plus each LED's colour falling off with distance from the
  LED's side of the gel, and lens vignetting;
- a contact response: for each LED, the change in Lambertian shading of the deformed
  surface relative to the flat gel, ``gain * colour_k * (n . l_k - n_flat . l_k)``, so a flat
  gel shows only the background;
- camera noise: zero-mean Gaussian pixel noise drawn from the render's generator, added after
  the variant and clipped to [0, 1], as tacto adds it to its 8-bit frames.

Where each parameter comes from with ``design="tacto"`` (the default).  **Published**: read from
tacto's file, directly or through geometry stated below; **measured**: fitted to real frames;
**assumed**: a guess.  No DIGIT parameter is measured: no real DIGIT frames ship with vqtouch.

=====================  ===========================  =================================================
parameter              tacto design                 source
=====================  ===========================  =================================================
LED colours            pure red, green, blue        published (``lights.colors`` times
                                                    ``lights.intensities``, all 1)
LED azimuths in the    -150 (red), -30 (green),     published geometry: polar angles 30/150/270
image                  90 (blue) degrees            degrees in the camera's y-z plane, seen through
                                                    the camera's orientation ([90, 0, -90], extrinsic
                                                    x-y-z Euler angles; image right = -y, image down
                                                    = -z with pyrender's camera axes)
LED elevation          40.4 degrees                 published geometry: the lights sit on a ring of
                                                    radius 20 mm, 17 mm in front of the gel's centre
                                                    (gel x 22 mm, light plane x 5 mm); seen from the
                                                    gel's centre, i.e. tacto's point lights made
                                                    directional
field of view          20 mm                        published geometry: the gel's width (20 x 30 mm),
                                                    inside the 25.4 mm the camera sees at the gel
                                                    (yfov 60 degrees at 22 mm); the file gives no
                                                    aspect ratio (tacto's default 3:4 portrait frame
                                                    would show 19 mm across)
camera noise std       7/255 on [0, 1]              published (``noise.color``: mean 0, std 7 on
                                                    [0, 255])
gel curvature          R 0.1 m, at most 5 mm        published, not modelled (the gel is flat here)
contact shading        Lambertian, gain 0.9         assumed (``response_gain``)
background             level 0.42, LED glow 0.25,   assumed (``background_level``, ``led_glow``,
                       vignetting 0.25              ``vignetting``)
gel blur               0.25 mm                      assumed (``gel_blur_mm``)
=====================  ===========================  =================================================

``design="builtin"`` is vqtouch's earlier hand-set model, all **assumed**: 16 mm field of view,
LEDs at 25 degrees elevation with the red one at azimuth 90 (the others at +120, +240), colours
with some cross-talk (:data:`LED_COLOURS`) and no camera noise.  Any option set explicitly
overrides the design's value; use a variant to model an individual sensor.
"""

from __future__ import annotations

import functools
import importlib.util
import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from vqtouch.core import BuildContext, PluginError

from .base import RenderedSensor, surface_slopes
from .digit_plugin import TACTO_INSTALL, DigitConfig

#: The built-in design's LED colours (red, green, blue with some cross-talk): assumed.
LED_COLOURS = ((1.0, 0.15, 0.1), (0.1, 1.0, 0.2), (0.15, 0.25, 1.0))


@dataclass(frozen=True)
class DigitDesign:
    """The DIGIT parameters a design fixes: the renderer's defaults for geometry, lights and noise.

    Angles are in degrees in the image plane (azimuth 0 = towards +column, 90 = towards +row,
    i.e. down the image); elevation is above the gel plane.  One entry per light, in the order
    red, green, blue.
    """

    source: str
    field_of_view_mm: float
    led_elevation_deg: tuple[float, ...]
    led_azimuth_deg: tuple[float, ...]
    led_colours: tuple[tuple[float, float, float], ...]
    camera_noise_std: float


#: vqtouch's earlier hand-set values, used with ``design="builtin"`` and when tacto's file is missing.
BUILTIN_DESIGN = DigitDesign(
    source="builtin",
    field_of_view_mm=16.0,
    led_elevation_deg=(25.0, 25.0, 25.0),
    led_azimuth_deg=(90.0, 210.0, 330.0),
    led_colours=LED_COLOURS,
    camera_noise_std=0.0,
)


# -- reading tacto's file ------------------------------------------------------------------------


def tacto_config_path() -> Path | None:
    """Path of ``config_digit.yml`` in the installed ``tacto`` package, or None when it is not installed.

    The package is located without importing it (its ``__init__`` needs pyrender and OpenGL).
    """
    try:
        spec = importlib.util.find_spec("tacto")
    except (ImportError, ValueError):
        return None
    for folder in (spec.submodule_search_locations or []) if spec is not None else []:
        path = Path(folder) / "config_digit.yml"
        if path.is_file():
            return path
    return None


def load_yaml(text: str) -> Any:
    """Parse YAML text safely (PyYAML's ``safe_load``); a malformed file is a one-line ValueError."""
    import yaml

    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        # PyYAML's messages span lines (with a caret under the column); errors here are one line.
        raise ValueError(" ".join(str(exc).split())) from None


def _rotation_xyz_deg(angles_deg: list[float]) -> np.ndarray:
    """Rotation matrix of extrinsic x-y-z Euler angles in degrees: about x first, then y, then z.

    This is the reading under which the file's own comment holds ("[90, 0, -90]: towards x-axis"
    for a camera that looks along -z at [0, 0, 0]); the intrinsic reading would look along +y.
    """
    ax, ay, az = (math.radians(a) for a in angles_deg)
    rx = np.array([[1, 0, 0], [0, math.cos(ax), -math.sin(ax)], [0, math.sin(ax), math.cos(ax)]])
    ry = np.array([[math.cos(ay), 0, math.sin(ay)], [0, 1, 0], [-math.sin(ay), 0, math.cos(ay)]])
    rz = np.array([[math.cos(az), -math.sin(az), 0], [math.sin(az), math.cos(az), 0], [0, 0, 1]])
    return rz @ ry @ rx


def design_from_tacto_config(document: dict[str, Any], source: str = "tacto") -> DigitDesign:
    """DIGIT's design from the parsed contents of tacto's ``config_digit.yml`` (see the module docstring).

    Light directions are taken from the gel's centre to each light and expressed in the image of
    the first camera, whose axes follow pyrender's convention (looks along its -z, +x right, +y up).
    Raises KeyError, TypeError or ValueError when the contents are not laid out as in tacto 0.0.3.
    """
    sensor = document["sensor"]
    camera, gel, lights, noise = sensor["camera"][0], sensor["gel"], sensor["lights"], sensor["noise"]["color"]
    rotation = _rotation_xyz_deg(camera["orientation"])
    forward, right, up = rotation @ [0, 0, -1], rotation @ [1, 0, 0], rotation @ [0, 1, 0]
    gel_centre = np.asarray(gel["origin"], dtype=float)
    distance_m = float(np.dot(gel_centre - np.asarray(camera["position"], dtype=float), forward))
    if distance_m <= 0:
        raise ValueError("the camera does not face the gel")

    origin = np.asarray(lights["origin"], dtype=float)
    if lights["polar"]:
        polar = lights["xrtheta"]
        offsets = [
            (x, r * math.cos(math.radians(t)), r * math.sin(math.radians(t)))
            for x, r, t in zip(polar["xs"], polar["rs"], polar["thetas"], strict=True)
        ]
    else:
        offsets = lights["xyz"]["coords"]
    colours = [
        tuple(float(c) * float(i) for c in colour)
        for colour, i in zip(lights["colors"], lights["intensities"], strict=True)
    ]
    if len(offsets) != 3 or len(colours) != 3 or any(len(c) != 3 for c in colours):
        raise ValueError(f"expected three RGB lights, got {len(offsets)} positions and {len(colours)} colours")
    elevations, azimuths = [], []
    for offset in offsets:
        to_light = origin + np.asarray(offset, dtype=float) - gel_centre
        towards_camera = -float(np.dot(to_light, forward))
        column, row = float(np.dot(to_light, right)), -float(np.dot(to_light, up))
        elevations.append(math.degrees(math.atan2(towards_camera, math.hypot(column, row))))
        azimuths.append(math.degrees(math.atan2(row, column)))

    if float(noise["mean"]) != 0:
        raise ValueError(f"a camera noise mean of {noise['mean']} is not modelled (only zero-mean noise)")
    # The largest gel square the camera shows: the gel's smaller side, unless the vertical field of
    # view at the gel's distance is smaller still.
    seen_m = 2 * distance_m * math.tan(math.radians(float(camera["yfov"])) / 2)
    field_of_view_mm = 1000 * min(float(gel["width"]), float(gel["height"]), seen_m)
    return DigitDesign(
        source=source,
        field_of_view_mm=field_of_view_mm,
        led_elevation_deg=tuple(elevations),
        led_azimuth_deg=tuple(azimuths),
        led_colours=tuple(colours),
        camera_noise_std=float(noise["std"]) / 255.0,
    )


@functools.lru_cache(maxsize=4)
def read_tacto_design(path: Path) -> DigitDesign:
    """DIGIT's published design read from tacto's ``config_digit.yml`` at ``path`` (cached per path).

    Raises PluginError (one line) when the file cannot be read or is not laid out as in tacto 0.0.3.
    """
    try:
        return design_from_tacto_config(load_yaml(Path(path).read_text()), source=f"tacto ({path})")
    except (OSError, KeyError, TypeError, ValueError, IndexError) as exc:
        detail = f"missing entry {exc}" if isinstance(exc, KeyError) else str(exc)
        raise PluginError(
            f"cannot read DIGIT's design from {path}: {detail}; reinstall it with {TACTO_INSTALL} "
            "or set design='builtin'"
        ) from None


_warned_missing_tacto = False


def digit_design(design: Literal["tacto", "builtin"]) -> DigitDesign:
    """The design behind the ``digit`` family's defaults: tacto's published one or vqtouch's built-in one.

    ``"tacto"`` without tacto's file installed falls back to :data:`BUILTIN_DESIGN` and warns once per
    process, naming the install command.
    """
    if design == "builtin":
        return BUILTIN_DESIGN
    path = tacto_config_path()
    if path is not None:
        return read_tacto_design(path)
    global _warned_missing_tacto
    if not _warned_missing_tacto:
        _warned_missing_tacto = True
        warnings.warn(
            f"DIGIT's published design (tacto's config_digit.yml) is not installed, so the digit sensor "
            f"family uses vqtouch's built-in values; {TACTO_INSTALL} to use it",
            UserWarning,
            stacklevel=2,
        )
    return BUILTIN_DESIGN


# -- the family ---------------------------------------------------------------------------------


class DigitSensor(RenderedSensor):
    """Three-LED Lambertian renderer of a DIGIT sensor, with camera noise.

    Geometry, light colours and noise come from ``config.design`` (:func:`digit_design`) unless
    the config sets them; ``design`` holds the values in use.  ``sensor_id`` is ``"digit"``.  No
    real DIGIT frames ship, so :meth:`reference_frames` is the contract's default (None).
    """

    sensor_id = "digit"

    def __init__(self, config: DigitConfig) -> None:
        super().__init__(config.variant, config.gel_blur_mm)
        self.config = config
        self.design = design = digit_design(config.design)
        self.field_of_view_mm = design.field_of_view_mm if config.field_of_view_mm is None else config.field_of_view_mm
        self.camera_noise_std = design.camera_noise_std if config.camera_noise_std is None else config.camera_noise_std
        elevations = design.led_elevation_deg if config.led_elevation_deg is None else (config.led_elevation_deg,) * 3
        azimuths = (
            design.led_azimuth_deg
            if config.led_azimuth_deg is None
            else tuple(config.led_azimuth_deg + 120 * k for k in range(3))
        )
        elevations, azimuths = [math.radians(e) for e in elevations], [math.radians(a) for a in azimuths]
        # Light directions (x = column, y = row, z = towards the camera), one per LED.
        directions = [
            (math.cos(a) * math.cos(e), math.sin(a) * math.cos(e), math.sin(e)) for a, e in zip(azimuths, elevations)
        ]
        self.register_buffer("light_L3", torch.tensor(directions), persistent=False)
        self.register_buffer("colour_L3", torch.tensor(design.led_colours), persistent=False)
        self.register_buffer("azimuth_L", torch.tensor(azimuths), persistent=False)

    def background(self, height: int, width: int, device: torch.device) -> torch.Tensor:
        ys, xs = torch.meshgrid(
            torch.linspace(-1, 1, height, device=device), torch.linspace(-1, 1, width, device=device), indexing="ij"
        )
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

    def render(self, height_mm_BHW: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """:meth:`RenderedSensor.render`, then the camera's pixel noise (std ``camera_noise_std``) drawn
        from ``generator`` after the variant's own draws, and a clip to [0, 1]."""
        images = super().render(height_mm_BHW, generator)
        if self.camera_noise_std == 0:
            return images
        noise = (
            torch.randn(images.shape, generator=generator, dtype=images.dtype)
            if generator is not None
            else torch.randn_like(images)
        )
        return (images + self.camera_noise_std * noise.to(images.device)).clamp(0.0, 1.0)


def build_digit(config: DigitConfig, context: BuildContext) -> DigitSensor:
    """Factory for the ``digit`` sensor family."""
    return DigitSensor(config)

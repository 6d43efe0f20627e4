"""Procedural contact objects: the embedded default scene library.

Each object class draws an object *surface* ``z(x, y)`` in millimetres over the sensor's
square field of view (higher = closer to the gel), at a random pose (rotation, offset),
scale and material colour.  Pressing it into the gel by ``depth`` gives the contact
indentation ``max(z - (max z - depth), 0)``, which a sensor family renders; the full
surface also drives the visual (camera) image of the same region.

Everything is a pure function of a ``torch.Generator``, so a dataset index always gives the
same sample.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from vqtouch.core.image_size import ImageSize, extent_hw, image_hw, pixel_centres_mm

Grid = tuple[torch.Tensor, torch.Tensor]  # (u, v) rotated/offset coordinates in mm, each (H, W)


def _uniform(generator: torch.Generator, low: float, high: float) -> float:
    return low + (high - low) * float(torch.rand(1, generator=generator))


def _dome(u: torch.Tensor, v: torch.Tensor, radius_mm: float) -> torch.Tensor:
    """A large spherical envelope so textured objects make a finite, curved contact patch."""
    return (radius_mm**2 - u**2 - v**2).clamp_min(0).sqrt() - radius_mm


def _smooth_noise(generator: torch.Generator, size: tuple[int, int], cells: int) -> torch.Tensor:
    coarse = torch.randn(1, 1, cells, cells, generator=generator)
    return F.interpolate(coarse, size=size, mode="bicubic", align_corners=True)[0, 0]


def _sphere(g: torch.Generator, u: torch.Tensor, v: torch.Tensor, scale: float) -> torch.Tensor:
    radius = _uniform(g, 2.0, 5.0) * scale
    return (radius**2 - u**2 - v**2).clamp_min(0).sqrt()


def _cylinder(g: torch.Generator, u: torch.Tensor, v: torch.Tensor, scale: float) -> torch.Tensor:
    radius = _uniform(g, 1.5, 4.0) * scale
    return (radius**2 - v**2).clamp_min(0).sqrt() + 0.02 * _dome(u, v, 40.0)


def _edge(g: torch.Generator, u: torch.Tensor, v: torch.Tensor, scale: float) -> torch.Tensor:
    rounding = _uniform(g, 0.15, 0.5) * scale
    return -rounding * F.softplus(v / rounding) + 0.2 * _dome(u, v, 30.0)


def _cube_corner(g: torch.Generator, u: torch.Tensor, v: torch.Tensor, scale: float) -> torch.Tensor:
    rounding = _uniform(g, 0.15, 0.5) * scale
    return -rounding * (F.softplus(u / rounding) + F.softplus(v / rounding)) + 0.2 * _dome(u, v, 30.0)


def _ridges(g: torch.Generator, u: torch.Tensor, v: torch.Tensor, scale: float) -> torch.Tensor:
    period = _uniform(g, 1.2, 2.5) * scale
    return 0.5 * torch.sin(math.pi * v / period) ** 2 + _dome(u, v, 9.0)


def _grating(g: torch.Generator, u: torch.Tensor, v: torch.Tensor, scale: float) -> torch.Tensor:
    period = _uniform(g, 0.5, 1.0) * scale
    return 0.25 * torch.sigmoid(6 * torch.sin(2 * math.pi * v / period)) + _dome(u, v, 10.0)


def _knurl(g: torch.Generator, u: torch.Tensor, v: torch.Tensor, scale: float) -> torch.Tensor:
    period = _uniform(g, 0.7, 1.4) * scale

    def triangle(w: torch.Tensor) -> torch.Tensor:
        return 1 - 2 * torch.abs(torch.remainder(w / period, 1.0) - 0.5)

    return 0.3 * torch.minimum(triangle(u + v), triangle(u - v)) + _dome(u, v, 9.0)


def _weave(g: torch.Generator, u: torch.Tensor, v: torch.Tensor, scale: float) -> torch.Tensor:
    pitch = _uniform(g, 0.6, 1.2) * scale
    over = torch.sigmoid(4 * torch.sin(math.pi * u / pitch) * torch.sin(math.pi * v / pitch))
    warp = torch.cos(math.pi * v / pitch) ** 2
    weft = torch.cos(math.pi * u / pitch) ** 2
    return 0.2 * (over * warp + (1 - over) * weft) + _dome(u, v, 10.0)


def _dots(g: torch.Generator, u: torch.Tensor, v: torch.Tensor, scale: float) -> torch.Tensor:
    pitch = _uniform(g, 1.2, 2.2) * scale
    bump = 0.35 * pitch
    du = torch.remainder(u, pitch) - pitch / 2
    dv = torch.remainder(v, pitch) - pitch / 2
    return (bump**2 - du**2 - dv**2).clamp_min(0).sqrt() + _dome(u, v, 12.0)


# Seven-segment layout on a unit cell (x in [0, 1], y in [0, 2]): (x0, y0, x1, y1) per segment.
_SEGMENTS = {
    "a": (0, 0, 1, 0),
    "b": (1, 0, 1, 1),
    "c": (1, 1, 1, 2),
    "d": (0, 2, 1, 2),
    "e": (0, 1, 0, 2),
    "f": (0, 0, 0, 1),
    "g": (0, 1, 1, 1),
}
_DIGIT_SEGMENTS = ["abcdef", "bc", "abged", "abgcd", "fgbc", "afgcd", "afgcde", "abc", "abcdefg", "abcdfg"]


def draw_digit(digit: int, u: torch.Tensor, v: torch.Tensor, height_mm: float, stroke_mm: float) -> torch.Tensor:
    """A seven-segment digit centred at (0, 0), ``height_mm`` tall, as a 0..1 mask with soft edges."""
    width = height_mm / 2
    x = u / width + 0.5
    y = v / (height_mm / 2) + 1.0
    stroke = stroke_mm / width
    mask = torch.zeros_like(u)
    for name in _DIGIT_SEGMENTS[digit]:
        x0, y0, x1, y1 = _SEGMENTS[name]
        # Distance from each point to the segment, in cell units.
        px, py = x - x0, y - y0
        dx, dy = x1 - x0, y1 - y0
        t = ((px * dx + py * dy) / (dx * dx + dy * dy)).clamp(0, 1)
        distance = torch.sqrt((px - t * dx) ** 2 + (py - t * dy) ** 2)
        mask = torch.maximum(mask, torch.sigmoid((stroke / 2 - distance) / (stroke * 0.15)))
    return mask


def _digits(g: torch.Generator, u: torch.Tensor, v: torch.Tensor, scale: float, digit: int = 0) -> torch.Tensor:
    height = _uniform(g, 5.0, 8.0) * scale
    return 0.3 * draw_digit(digit, u, v, height, 0.18 * height) + _dome(u, v, 14.0)


def _rock(g: torch.Generator, u: torch.Tensor, v: torch.Tensor, scale: float) -> torch.Tensor:
    size = u.shape
    relief = sum(
        _smooth_noise(g, size, cells) * amplitude for cells, amplitude in ((4, 0.5), (8, 0.25), (16, 0.12), (32, 0.06))
    )
    return 0.6 * relief * scale + _dome(u, v, 6.0 * scale)


def _cloth_folds(g: torch.Generator, u: torch.Tensor, v: torch.Tensor, scale: float) -> torch.Tensor:
    surface = torch.zeros_like(u)
    for _ in range(3):
        angle = _uniform(g, 0, math.pi)
        wavelength = _uniform(g, 3.0, 7.0) * scale
        phase = _uniform(g, 0, 2 * math.pi)
        surface = surface + 0.4 * torch.sin(
            2 * math.pi * (u * math.cos(angle) + v * math.sin(angle)) / wavelength + phase
        )
    return surface + 0.03 * _smooth_noise(g, u.shape, 24) + _dome(u, v, 14.0)


@dataclass(frozen=True)
class ObjectClass:
    """One class of the scene library: how to draw its surface and what it looks like."""

    name: str
    material: str
    albedo: tuple[float, float, float]
    specular: float
    texture: str
    draw: Callable[..., torch.Tensor]


OBJECT_CLASSES: tuple[ObjectClass, ...] = (
    ObjectClass("sphere", "polished steel", (0.62, 0.64, 0.68), 0.8, "brushed", _sphere),
    ObjectClass("cylinder", "red plastic", (0.75, 0.18, 0.15), 0.4, "plain", _cylinder),
    ObjectClass("edge", "oak wood", (0.62, 0.45, 0.26), 0.1, "wood", _edge),
    ObjectClass("cube_corner", "painted metal", (0.2, 0.35, 0.7), 0.5, "plain", _cube_corner),
    ObjectClass("ridges", "black rubber", (0.12, 0.12, 0.13), 0.15, "speckle", _ridges),
    ObjectClass("grating", "aluminium", (0.75, 0.76, 0.78), 0.7, "brushed", _grating),
    ObjectClass("knurl", "tool steel", (0.45, 0.46, 0.48), 0.6, "brushed", _knurl),
    ObjectClass("weave", "cotton fabric", (0.8, 0.72, 0.55), 0.02, "threads", _weave),
    ObjectClass("dots", "yellow plastic", (0.9, 0.78, 0.1), 0.4, "plain", _dots),
    ObjectClass("digits", "embossed tin", (0.7, 0.7, 0.62), 0.5, "ink", _digits),
    ObjectClass("rock", "granite", (0.5, 0.46, 0.42), 0.05, "speckle", _rock),
    ObjectClass("cloth_folds", "blue denim", (0.2, 0.3, 0.55), 0.02, "threads", _cloth_folds),
)
CLASS_NAMES: tuple[str, ...] = tuple(c.name for c in OBJECT_CLASSES)


@dataclass
class Contact:
    """One pressed object: its indentation, full surface and what was drawn."""

    class_index: int
    indentation_mm_HW: torch.Tensor
    surface_mm_HW: torch.Tensor
    depth_mm: float
    angle_deg: float
    offset_mm: tuple[float, float]
    scale: float
    detail: str

    def description(self, class_name: str, material: str) -> str:
        """A short text description for text conditioning."""
        subject = f"the digit {self.detail}" if self.detail else class_name.replace("_", " ")
        return f"{subject} in {material}, pressed {self.depth_mm:.2f} mm into the gel"


def sample_contact(
    object_class: ObjectClass,
    class_index: int,
    generator: torch.Generator,
    size: ImageSize,
    field_of_view_mm: float | tuple[float, float],
    depth_range_mm: tuple[float, float] = (0.2, 1.0),
) -> Contact:
    """Draw one object of ``object_class`` at a random pose and press it into the gel.

    ``size``: the height map's S (S x S) or (height, width); ``field_of_view_mm``: the side of the
    square area it covers, or its (rows, columns) extent in mm (``SensorFamily.imaged_extent_mm``).
    """
    rows_mm, cols_mm = extent_hw(field_of_view_mm)
    angle = _uniform(generator, 0.0, 2 * math.pi)
    offset = (_uniform(generator, -0.15, 0.15) * cols_mm, _uniform(generator, -0.15, 0.15) * rows_mm)
    scale = _uniform(generator, 0.8, 1.25)
    y, x = pixel_centres_mm(*image_hw(size), (rows_mm, cols_mm))
    x, y = x - offset[0], y - offset[1]
    u = x * math.cos(angle) + y * math.sin(angle)
    v = -x * math.sin(angle) + y * math.cos(angle)
    detail = ""
    if object_class.draw is _digits:
        digit = int(torch.randint(0, 10, (1,), generator=generator))
        surface = _digits(generator, u, v, scale, digit=digit)
        detail = str(digit)
    else:
        surface = object_class.draw(generator, u, v, scale)
    top = surface.max()
    relief = float(top - surface.min())
    depth = min(_uniform(generator, *depth_range_mm), max(relief, 1e-3))
    indentation = (surface - (top - depth)).clamp_min(0)
    return Contact(class_index, indentation, surface, depth, math.degrees(angle), offset, scale, detail)

"""Image sizes: ``S`` (S x S pixels) or ``(height, width)``, and their config option.

Kept apart from the image utilities (file reading and writing) so that every core module,
the build context included, can use it without an import cycle."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated

from pydantic import BeforeValidator
from pydantic_core import PydanticCustomError

#: An image size: ``S`` for S x S pixels, or ``(height, width)`` (e.g. (240, 320), a sensor's native aspect).
ImageSize = int | tuple[int, int]

if TYPE_CHECKING:
    import torch


def image_hw(size: ImageSize) -> tuple[int, int]:
    """``(height, width)`` of an image size (``S`` -> ``(S, S)``)."""
    if isinstance(size, int):
        return size, size
    height, width = size
    return int(height), int(width)


def extent_hw(extent_mm: float | tuple[float, float]) -> tuple[float, float]:
    """``(rows, columns)`` in mm of an imaged area given as a square's side or as that pair."""
    if isinstance(extent_mm, (int, float)):
        return float(extent_mm), float(extent_mm)
    rows_mm, cols_mm = extent_mm
    return float(rows_mm), float(cols_mm)


def pixel_centres_mm(
    height: int, width: int, extent_mm: float | tuple[float, float]
) -> tuple[torch.Tensor, torch.Tensor]:
    """(ys, xs), each (height, width): the centre of every pixel of a height x width image of a
    centred area ``extent_mm`` (a side, or (rows, columns)), in mm from the area's centre."""
    import torch

    rows_mm, cols_mm = extent_hw(extent_mm)
    axis_rows = (torch.arange(height, dtype=torch.float32) + 0.5) / height * rows_mm - rows_mm / 2
    axis_cols = (torch.arange(width, dtype=torch.float32) + 0.5) / width * cols_mm - cols_mm / 2
    ys, xs = torch.meshgrid(axis_rows, axis_cols, indexing="ij")
    return ys, xs


def square_or_pair(height: int, width: int) -> ImageSize:
    """The canonical :data:`ImageSize` of height x width: an int when square, else the pair."""
    return height if height == width else (height, width)


def _checked_size(value: object) -> ImageSize:
    """A config value as a canonical :data:`ImageSize`, or one error saying what is allowed (a union of
    two pydantic types would report a line per alternative)."""
    sides = list(value) if isinstance(value, (list, tuple)) else [value]
    # Strict integers: ``true`` is not 1 and "64" is not 64, in a config that must train as written.
    if (
        len(sides) in (1, 2)
        and all(type(side) is int and 8 <= side <= 4096 for side in sides)
        and not (len(sides) == 1 and isinstance(value, (list, tuple)))
    ):
        return square_or_pair(sides[0], sides[-1])
    raise PydanticCustomError(
        "image_size",
        "expected a side S (S x S pixels) or [height, width] such as "
        "[240, 320], whole numbers of pixels from 8 to 4096",
    )


#: An :data:`ImageSize` config value: ``64`` or ``[240, 320]`` (height, width); a square pair reads as its int.
ImageSizeOption = Annotated[int | tuple[int, int], BeforeValidator(_checked_size)]


def size_text(size: ImageSize) -> str:
    """``"64"`` or ``"240x320"`` (height x width), for messages and labels."""
    height, width = image_hw(size)
    return str(height) if height == width else f"{height}x{width}"


def image_size_argument(text: str) -> ImageSize:
    """``--image-size`` on a command line: ``64`` or ``240x320`` (height x width)."""
    import argparse

    try:
        sides = [int(part) for part in text.lower().replace(",", "x").split("x")]
        return _checked_size(sides if len(sides) > 1 else sides[0])
    except (ValueError, PydanticCustomError):
        raise argparse.ArgumentTypeError(
            f"{text!r}: expected a side S (S x S pixels) or HEIGHTxWIDTH such as 240x320, each 8 to 4096"
        ) from None

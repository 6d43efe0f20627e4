"""Reading image files into tensors and writing image batches to PNG files (Pillow, imported only
when an image is read or written)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from vqtouch.core.checkpoint import atomic_write
from vqtouch.core.errors import ConfigError, DatasetError
from vqtouch.plugins.utils.image_options import (
    _GREYSCALE_ALLOWED,
)  # noqa: F401
from vqtouch.core.image_size import ImageSize, image_hw

#: How an image is brought to the requested aspect ratio: see ``ImageLoader.crop``.
CropMode = Literal["center", "top", "stretch"]


def image_grid(images_B3HW: torch.Tensor, columns: int | None = None, padding: int = 2) -> torch.Tensor:
    """Tile a batch of images in [0, 1] into one (3, H', W') image with white padding."""
    if images_B3HW.ndim != 4 or images_B3HW.shape[1] not in (1, 3):
        raise ValueError(f"expected images (B, 1|3, H, W), got {tuple(images_B3HW.shape)}")
    images = images_B3HW.detach().float().cpu().clamp(0, 1).expand(-1, 3, -1, -1)
    batch, _, height, width = images.shape
    columns = columns or math.ceil(math.sqrt(batch))
    rows = math.ceil(batch / columns)
    grid = torch.ones(3, rows * (height + padding) + padding, columns * (width + padding) + padding)
    for index in range(batch):
        row, col = divmod(index, columns)
        top, left = padding + row * (height + padding), padding + col * (width + padding)
        grid[:, top : top + height, left : left + width] = images[index]
    return grid


def save_png(image_3HW: torch.Tensor, path: str | Path) -> Path:
    """Save one (3, H, W) image in [0, 1] as an 8-bit PNG, atomically."""
    from PIL import Image

    if not torch.isfinite(image_3HW).all():
        raise ValueError(f"refusing to write {path}: the image contains NaN or Inf")
    array = (image_3HW.detach().float().cpu().clamp(0, 1) * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()
    return atomic_write(Path(path), lambda tmp: Image.fromarray(array).save(tmp, format="PNG"))


_GREYSCALE_MODES = frozenset({"1", "L", "LA", "La"})
_COLOUR_MODES = frozenset({"RGB", "RGBA", "RGBa", "RGBX", "CMYK", "YCbCr", "LAB", "HSV", "P", "PA"})


def mode_problem(path: Path, mode: str, allow_greyscale: bool) -> str | None:
    """Why an image of Pillow ``mode`` cannot be used, or None; transparency needs the pixels."""
    if mode in _GREYSCALE_MODES:
        if allow_greyscale:
            return None
        return (
            f"image {path} is greyscale (mode {mode}); to copy it into 3 channels pass --allow-greyscale (commands "
            "that read images) or set allow_greyscale=true (dataset readers)"
        )
    if mode not in _COLOUR_MODES:
        return f"image {path} has unsupported mode {mode}; expected 8-bit RGB"
    return None


def crop_box(
    width: int, height: int, mode: CropMode, aspect_hw: tuple[int, int] = (1, 1)
) -> tuple[float, float, float, float]:
    """The region (left, top, right, bottom) of a width x height image that becomes an output of
    ``aspect_hw``'s aspect ratio: the largest such box, centred ("center") or at the top ("top"),
    or the whole image ("stretch")."""
    if mode == "stretch":
        return (0.0, 0.0, float(width), float(height))
    out_h, out_w = aspect_hw
    # The largest out_h:out_w box inside the image.
    box_w, box_h = (
        (float(width), width * out_h / out_w)
        if width * out_h <= height * out_w
        else (height * out_w / out_h, float(height))
    )
    left = (width - box_w) / 2
    top = (height - box_h) / 2 if mode == "center" else 0.0
    return (left, top, left + box_w, top + box_h)


@dataclass(frozen=True)
class ImageLoader:
    """Decodes one image file into a float tensor (3, H, W) in [0, 1], (H, W) = ``image_hw(size)``.

    Colour modes other than RGB are converted; RGBA is accepted only when fully opaque (the
    conversion is then lossless); greyscale is replicated into 3 channels only when
    ``allow_greyscale`` is set.  Every failure is a DatasetError naming the file.
    """

    size: ImageSize
    crop: CropMode = "center"
    #: None: as the command asks (:func:`greyscale_allowed`, ``--allow-greyscale``); a reader's option sets it.
    allow_greyscale: bool | None = None

    def load(self, path: Path) -> torch.Tensor:
        """The image at ``path`` as a float32 tensor (3, H, W) in [0, 1]."""
        from PIL import Image

        height, width = image_hw(self.size)
        try:
            with Image.open(path) as image:
                # JPEG only: decode at a reduced scale that is still >= size (much faster, same result).
                image.draft(None, (width, height))
                image.load()
                rgb = self._as_rgb(image, path)
                # One resampling pass over the crop box: the same as resizing and cropping
                # afterwards, without rounding twice.  Pillow's resize antialiases.
                square = rgb.resize(
                    (width, height),
                    Image.Resampling.BICUBIC,
                    box=crop_box(rgb.width, rgb.height, self.crop, (height, width)),
                )
        except DatasetError:
            raise
        except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as exc:
            raise DatasetError(f"cannot decode image {path}: {type(exc).__name__}: {exc}") from None
        array = np.asarray(square, dtype=np.uint8)
        return torch.from_numpy(array.copy()).permute(2, 0, 1).float().div_(255.0)

    def problem(self, path: Path) -> str | None:
        """Why ``path`` cannot be loaded, or None when it decodes."""
        try:
            self.load(path)
        except DatasetError as exc:
            return str(exc)
        return None

    def _as_rgb(self, image: Any, path: Path) -> Any:
        mode = image.mode
        if mode == "RGB":
            return image
        allowed = self.allow_greyscale if self.allow_greyscale is not None else _GREYSCALE_ALLOWED.get()
        problem = mode_problem(path, mode, allowed)
        if problem:
            raise DatasetError(problem)
        if mode in _GREYSCALE_MODES:
            return self._drop_opaque_alpha(image, path) if "A" in mode or "a" in mode else image.convert("RGB")
        if mode == "P":
            # A palette image may mark one entry transparent; only then does it carry alpha.
            return (
                self._drop_opaque_alpha(image.convert("RGBA"), path)
                if "transparency" in image.info
                else image.convert("RGB")
            )
        if mode in {"RGBA", "RGBa", "PA"}:
            return self._drop_opaque_alpha(image, path)
        return image.convert("RGB")

    def _drop_opaque_alpha(self, image: Any, path: Path) -> Any:
        alpha = image.getchannel(image.getbands()[-1])
        lowest, _ = alpha.getextrema()
        if lowest < 255:
            raise DatasetError(
                f"image {path} has transparent pixels (mode {image.mode}, alpha down to {lowest}); "
                f"expected an opaque RGB image"
            )
        return image.convert("RGB")


def read_condition_image(value: str | Path, sample_key: str, size: ImageSize) -> torch.Tensor:
    """An image condition a user named by path (``vqtouch generate --visual PATH``): decoded,
    centre-cropped to ``size``'s aspect and resized to it, in [0, 1]; a one-line ConfigError naming
    the option (``--visual`` for a visual condition, ``--tactile`` for the others) when it cannot."""
    flag = "visual" if sample_key == "visual" else "tactile"
    path = Path(str(value))
    if not path.is_file():
        raise ConfigError(f"--{flag} {value}: no such image file")
    try:
        return ImageLoader(size=size).load(path)
    except DatasetError as exc:
        raise ConfigError(f"--{flag}: {exc}") from None

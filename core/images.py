"""Writing image batches to PNG files (Pillow, imported only when an image is written)."""

from __future__ import annotations

import math
from pathlib import Path

import torch

from .checkpoint import atomic_write


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
        grid[:, top:top + height, left:left + width] = images[index]
    return grid


def save_png(image_3HW: torch.Tensor, path: str | Path) -> Path:
    """Save one (3, H, W) image in [0, 1] as an 8-bit PNG, atomically."""
    from PIL import Image

    if not torch.isfinite(image_3HW).all():
        raise ValueError(f"refusing to write {path}: the image contains NaN or Inf")
    array = (image_3HW.detach().float().cpu().clamp(0, 1) * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()
    return atomic_write(Path(path), lambda tmp: Image.fromarray(array).save(tmp, format="PNG"))

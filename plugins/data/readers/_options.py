"""The options every dataset reader shares (:class:`ReaderConfig`), light so that the readers' plugin
modules declare their configs without importing torch (the readers' machinery is in _io.py)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from vqtouch.core import PluginConfig
from vqtouch.core.image_size import ImageSizeOption

#: vqtouch.plugins.utils.images.CropMode, spelled out here because that module imports torch (a test checks
#: that the two agree).
CropMode = Literal["center", "top", "stretch"]


class ReaderConfig(PluginConfig):
    """Options shared by every dataset reader; each reader narrows ``name`` and adds its own."""

    root: str = Field(
        "",
        description="Dataset folder (see the reader's layout). Required: building fails "
        "naming it when it is empty or missing.",
    )
    image_size: ImageSizeOption | None = Field(
        None,
        description="Size of the images returned, in pixels: S for (3, S, S), or [height, width] such as "
        "[240, 320] for a sensor's native 3:4 frames; null uses the experiment's data.image_size.",
    )
    crop: CropMode = Field(
        "center",
        description="How an image is brought to image_size's aspect: 'center' keeps the "
        "largest centred region of that aspect and resizes it, 'top' keeps "
        "the top instead, 'stretch' resizes the whole image, ignoring the "
        "aspect ratio.",
    )
    lenient: bool = Field(
        False,
        description="Skip bad samples (missing or corrupt files, bad labels, broken pairs) "
        "with one warning that counts them, instead of failing. Decodes every "
        "image once at construction to find corrupt ones (slow on large sets); "
        "strict builds only open each image's header, which misses truncated "
        "pixel data until the image is loaded.",
    )
    header_cache: bool = Field(
        True,
        description="Remember the image headers checked at construction by file path, "
        "size, modification and change time, in "
        "$XDG_CACHE_HOME/vqtouch/image_headers/ (default "
        "~/.cache/vqtouch/image_headers/), so building the same dataset "
        "again opens only new or changed files; false opens every header "
        "each time and writes nothing.",
    )
    allow_greyscale: bool = Field(
        False,
        description="Accept greyscale images by copying them into 3 channels; "
        "otherwise they are errors (skips when lenient).",
    )
    max_samples: int | None = Field(
        None,
        ge=1,
        le=1_000_000_000,
        description="Keep only the first N usable samples in list order (quick runs); null keeps all.",
    )

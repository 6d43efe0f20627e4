"""A sensor's folder of images, read one way wherever one is given (`cluster`, `adapt`,
`fewshot`, `reconstruct --images`): an ``index.csv`` written by ``vqtouch data render``, else the
image files directly in the folder, else one sub-folder per class; every image of one
resolution."""

from __future__ import annotations

import warnings
from pathlib import Path

import torch

from vqtouch.core import DatasetError, PluginHost, VqtouchWarning
from vqtouch.plugins.utils.image_options import skipping_bad_images
from vqtouch.core.image_size import ImageSize

#: What a command that reads a sensor's folder offers for a file it cannot use.
LENIENT_ADVICE = "pass --lenient to skip the images that cannot be used"
#: The index ``vqtouch data render`` writes beside its tactile/ and visual/ folders.
EXPORT_INDEX = "index.csv"


def sensor_folder_files(path: Path, host: PluginHost) -> list[Path]:
    """The image files of a sensor's folder, in a stable order, read as the ``image_folder`` reader
    reads it: the tactile images an ``index.csv`` lists (what ``vqtouch data render`` writes: its
    visual images and preview beside them are not the sensor's); else the images directly in the
    folder (natural order); else one sub-folder per class, read recursively.  A folder with none of
    them is a one-line DatasetError naming the layouts read."""
    from vqtouch.plugins.data.readers import list_images

    options = {"name": "image_folder", "root": str(path)}
    if (path / EXPORT_INDEX).is_file():
        options["csv"] = EXPORT_INDEX
    elif direct := list_images(path):
        return usable_images(path, direct) if skipping_bad_images() else direct
    elif not any(sub.is_dir() and not sub.name.startswith(".") for sub in path.iterdir()):
        raise DatasetError(
            f"{path}: no image files (png, jpg, ...) in this folder, no {EXPORT_INDEX} and no class sub-folders; "
            "give the folder that holds the sensor's images"
        )
    if skipping_bad_images():
        options["lenient"] = True
    dataset = host.build("dataset", options)
    return [dataset.base / record.tactile for record in dataset.records]


def usable_images(folder: Path, files: list[Path]) -> list[Path]:
    """``files`` less those that do not decode or cannot be used (``--lenient``), with one warning
    naming how many and the first; a DatasetError when none is left."""
    from vqtouch.plugins.utils.images import ImageLoader

    loader, kept, problems = ImageLoader(size=8), [], []
    for file in files:
        try:
            loader.load(file)
        except DatasetError as exc:
            problems.append(str(exc))
            continue
        kept.append(file)
    if not kept:
        raise DatasetError(f"{folder}: none of its {len(files)} images can be used (first: {problems[0]})")
    if problems:
        warnings.warn(
            f"{folder}: skipped {len(problems)} of {len(files)} images (--lenient); first: {problems[0]}",
            VqtouchWarning,
            stacklevel=2,
        )
    return kept


def folder_of(spec: str) -> Path | None:
    """The folder ``spec`` names, or None when it is a sensor name or JSON (or no folder)."""
    if spec.lstrip().startswith("{"):
        return None
    try:
        path = Path(spec).expanduser()
        return path if path.is_dir() else None
    except OSError:  # e.g. a name too long to be a path
        return None


def check_one_resolution(folder: Path, files: list[Path]) -> None:
    """Refuse a folder whose images have different sizes: one sensor's frames share one camera
    resolution, and resizing a mix would silently stretch some of them."""
    from PIL import Image

    sizes: dict[tuple[int, int], Path] = {}
    for file in files:
        try:
            with Image.open(file) as image:
                sizes.setdefault(image.size, file)
        except (OSError, ValueError) as exc:
            raise DatasetError(f"cannot decode image {file}: {type(exc).__name__}: {exc}; {LENIENT_ADVICE}") from None
        if len(sizes) > 1:
            (a, first), (b, second) = list(sizes.items())[:2]
            raise DatasetError(
                f"{folder}: images of different sizes ({first.name} is {a[0]}x{a[1]}, {second.name} is "
                f"{b[0]}x{b[1]}); a sensor's frames share one resolution: give each sensor its own "
                "folder, or resize them to one size first"
            )


def holds_images_directly(path: Path) -> bool:
    """Whether the folder ``path`` holds image files itself or a ``vqtouch data render`` index: the
    layouts the ``image_folder`` reader (one sub-folder per class) does not read on its own."""
    from vqtouch.plugins.data.readers import list_images

    return (path / EXPORT_INDEX).is_file() or bool(list_images(path))


def load_sensor_folder(
    path: Path, host: PluginHost, image_size: ImageSize, *, count: int | None = None, files: list[Path] | None = None
) -> torch.Tensor:
    """(N, 3, H, W) images in [0, 1] at ``image_size`` of the sensor folder ``path`` (its first ``count``
    files as :func:`sensor_folder_files` orders them, or the given ``files``); a one-line DatasetError
    for an empty folder, mixed resolutions or a file that does not decode (named)."""
    from vqtouch.plugins.utils.images import ImageLoader

    files = files if files is not None else sensor_folder_files(path, host)[:count]
    if not files:
        raise DatasetError(f"{path}: no image files (png, jpg, ...) in this folder")
    check_one_resolution(path, files)
    loader = ImageLoader(size=image_size)
    try:
        return torch.stack([loader.load(file) for file in files])  # DatasetError names the file that does not decode
    except DatasetError as exc:
        raise DatasetError(f"{exc}; {LENIENT_ADVICE}") from None

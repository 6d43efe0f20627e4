"""Shared machinery of the dataset readers: options, image decoding, file checks, skipping.

Every reader follows the same plan, implemented once here:

1. check the root folder and the dataset's own list/CSV files (:func:`require_root`,
   :func:`require_file`, :func:`read_list_lines`, :func:`read_csv_rows`, :func:`read_json`);
2. turn each listed entry into a :class:`SampleRecord` (paths, label, text, id), checking that
   its files exist with :class:`FileIndex` and reporting bad entries to a :class:`SkipLog`,
   which raises :class:`~vqtouch.core.DatasetError` in strict mode and records the reason when
   ``lenient`` is set;
3. :func:`collect_records` keeps the good records (decoding every image once when lenient, so
   corrupt files are skipped too), applies ``max_samples``, refuses an empty split and emits the
   single warning that counts what was skipped;
4. :class:`RecordDataset` decodes images on access with :class:`ImageLoader`.

Pillow is imported inside the functions that decode, so importing a reader stays cheap.
"""

from __future__ import annotations

import csv
import json
import os
import re
import warnings
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from pydantic import Field

from vqtouch.core import DatasetError, PluginConfig, TactileDataset
from vqtouch.core.progress import progress

IMAGE_SUFFIXES = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".webp", ".tif", ".tiff"})
CropMode = Literal["center", "top", "stretch"]

# Reasons quoted in the lenient-mode warning; the count covers the rest.
REASONS_SHOWN = 3
# Reference frames repeat across many samples (one per recording or trajectory).
REFERENCE_CACHE_SIZE = 64


class ReaderConfig(PluginConfig):
    """Options shared by every dataset reader; each reader narrows ``name`` and adds its own."""

    root: str = Field("", description="Dataset folder (see the reader's layout). Required: building fails "
                                      "naming it when it is empty or missing.")
    image_size: int | None = Field(None, ge=8, le=4096,
                                   description="Side S of the square (3, S, S) images returned, in pixels; null "
                                               "uses the experiment's data.image_size.")
    crop: CropMode = Field("center", description="How an image is made square: 'center' resizes the shorter side "
                                                 "to image_size and keeps the middle, 'top' keeps the top instead, "
                                                 "'stretch' resizes the whole image, ignoring the aspect ratio.")
    lenient: bool = Field(False, description="Skip bad samples (missing or corrupt files, bad labels, broken pairs) "
                                             "with one warning that counts them, instead of failing. Decodes every "
                                             "image once at construction to find corrupt ones (slow on large sets).")
    allow_greyscale: bool = Field(False, description="Accept greyscale images by copying them into 3 channels; "
                                                     "otherwise they are errors (skips when lenient).")
    max_samples: int | None = Field(None, ge=1, le=1_000_000_000,
                                    description="Keep only the first N usable samples in list order (quick runs); "
                                                "null keeps all.")


class SkippedSamplesWarning(UserWarning):
    """Issued once per lenient dataset build that skipped bad samples."""


# --------------------------------------------------------------------------------------------
# Bad entries: strict raises, lenient skips and counts
# --------------------------------------------------------------------------------------------
class SkipLog:
    """Decides the fate of a bad entry: an error in strict mode, a counted skip when lenient."""

    def __init__(self, reader: str, lenient: bool) -> None:
        self.reader = reader
        self.lenient = lenient
        self.reasons: list[str] = []
        self.count = 0

    def reject(self, reason: str, samples: int = 1) -> None:
        """Report a bad entry holding ``samples`` samples; raises DatasetError unless lenient."""
        if not self.lenient:
            raise DatasetError(f"{self.reader}: {reason} (set lenient=true to skip bad samples)")
        self.reasons.append(reason)
        self.count += samples

    def summary(self) -> str:
        """One line: how many samples were skipped and the first few reasons."""
        shown = "; ".join(self.reasons[:REASONS_SHOWN])
        hidden = len(self.reasons) - REASONS_SHOWN
        more = f"; and {hidden} more problem(s)" if hidden > 0 else ""
        return f"{self.reader}: skipped {self.count} bad sample(s): {shown}{more}"

    def warn_if_any(self) -> None:
        """Emit the single summary warning, if anything was skipped."""
        if self.reasons:
            warnings.warn(self.summary(), SkippedSamplesWarning, stacklevel=3)


# --------------------------------------------------------------------------------------------
# Files and folders
# --------------------------------------------------------------------------------------------
def require_root(config: ReaderConfig, layout: str) -> Path:
    """The configured root folder; a clear DatasetError when it is unset or missing."""
    if not config.root.strip():
        raise DatasetError(f"dataset {config.name!r} needs its folder: set dataset.root=/path/to/data "
                           f"(expected layout: {layout})")
    root = Path(config.root).expanduser()
    if not root.is_dir():
        raise DatasetError(f"{config.name}: root folder {root} does not exist or is not a folder "
                           f"(expected layout: {layout})")
    return root


def resolve_under(path_text: str, root: Path) -> Path:
    """A configured path: absolute as given (``~`` expanded), otherwise relative to ``root``."""
    path = Path(path_text).expanduser()
    return path if path.is_absolute() else root / path


def require_file(path: Path, reader: str, what: str) -> Path:
    """``path`` if it is a file, else a DatasetError naming it and what it should hold."""
    if not path.is_file():
        raise DatasetError(f"{reader}: missing {what}: {path}")
    return path


def require_folder(path: Path, reader: str, what: str) -> Path:
    """``path`` if it is a folder, else a DatasetError naming it and what it should hold."""
    if not path.is_dir():
        raise DatasetError(f"{reader}: missing {what} folder: {path}")
    return path


def _read_text(path: Path, reader: str) -> str:
    try:
        # utf-8-sig drops the byte-order mark that spreadsheet programs put in CSVs.
        return path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise DatasetError(f"{reader}: missing file {path}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{reader}: cannot read {path}: {exc}") from None


def read_list_lines(path: Path, reader: str) -> list[tuple[int, str]]:
    """Non-blank lines of a text list, stripped, with their 1-based line numbers."""
    lines = _read_text(path, reader).splitlines()
    return [(number, line.strip()) for number, line in enumerate(lines, start=1) if line.strip()]


def read_csv_rows(path: Path, reader: str) -> list[tuple[int, list[str]]]:
    """Non-empty rows of a CSV file with the line number each row starts on (header included)."""
    text = _read_text(path, reader)
    rows = []
    try:
        parser = csv.reader(text.splitlines())
        for row in parser:
            if any(cell.strip() for cell in row):
                rows.append((parser.line_num, [cell.strip() for cell in row]))
    except csv.Error as exc:
        raise DatasetError(f"{reader}: malformed CSV {path}: {exc}") from None
    return rows


def read_json(path: Path, reader: str) -> Any:
    """A parsed JSON file; syntax errors name the file, line and column."""
    try:
        return json.loads(_read_text(path, reader))
    except json.JSONDecodeError as exc:
        raise DatasetError(f"{reader}: malformed JSON {path} line {exc.lineno} column {exc.colno}: {exc.msg}") from None


def natural_key(name: str) -> tuple[Any, ...]:
    """Sort key that orders embedded numbers by value (frame2 before frame10)."""
    return tuple(int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name))


def is_image_file(path: Path) -> bool:
    """Whether ``path`` names a visible file with a known image suffix."""
    return path.suffix.lower() in IMAGE_SUFFIXES and not path.name.startswith(".") and path.is_file()


def list_images(folder: Path, *, recursive: bool = False) -> list[Path]:
    """Image files in ``folder`` (optionally its sub-folders), in natural order of their relative paths."""
    candidates = folder.rglob("*") if recursive else folder.iterdir()
    images = [path for path in candidates if is_image_file(path)]
    return sorted(images, key=lambda path: natural_key(path.relative_to(folder).as_posix()))


def visible_subfolders(folder: Path) -> list[Path]:
    """Sub-folders of ``folder`` whose names do not start with a dot, sorted by name."""
    return sorted((path for path in folder.iterdir() if path.is_dir() and not path.name.startswith(".")),
                  key=lambda path: path.name)


class FileIndex:
    """Answers "does this file exist?" from one directory listing per folder.

    Lists name up to hundreds of thousands of frames spread over a few hundred folders: one
    ``scandir`` per folder is far cheaper than one ``stat`` per file on network storage.
    """

    def __init__(self) -> None:
        self._names_by_folder: dict[Path, frozenset[str]] = {}

    def exists(self, path: Path) -> bool:
        """Whether ``path`` is an existing file (or a link to one)."""
        folder = path.parent
        names = self._names_by_folder.get(folder)
        if names is None:
            names = self._list(folder)
            self._names_by_folder[folder] = names
        return path.name in names

    @staticmethod
    def _list(folder: Path) -> frozenset[str]:
        try:
            with os.scandir(folder) as entries:
                return frozenset(entry.name for entry in entries if entry.is_file())
        except (FileNotFoundError, NotADirectoryError):
            return frozenset()
        except OSError as exc:
            raise DatasetError(f"cannot list folder {folder}: {exc}") from None


# --------------------------------------------------------------------------------------------
# Images
# --------------------------------------------------------------------------------------------
_GREYSCALE_MODES = frozenset({"1", "L", "LA", "La"})
_COLOUR_MODES = frozenset({"RGB", "RGBA", "RGBa", "RGBX", "CMYK", "YCbCr", "LAB", "HSV", "P", "PA"})


def crop_box(width: int, height: int, mode: CropMode) -> tuple[float, float, float, float]:
    """The region of a width x height image that becomes the square output."""
    if mode == "stretch":
        return (0.0, 0.0, float(width), float(height))
    side = min(width, height)
    left = (width - side) / 2
    top = (height - side) / 2 if mode == "center" else 0.0
    return (left, top, left + side, top + side)


@dataclass(frozen=True)
class ImageLoader:
    """Decodes one image file into a float tensor (3, size, size) in [0, 1].

    Colour modes other than RGB are converted; RGBA is accepted only when fully opaque (the
    conversion is then lossless); greyscale is replicated into 3 channels only when
    ``allow_greyscale`` is set.  Every failure is a DatasetError naming the file.
    """

    size: int
    crop: CropMode = "center"
    allow_greyscale: bool = False

    def load(self, path: Path) -> torch.Tensor:
        """The image at ``path`` as a float32 tensor (3, size, size) in [0, 1]."""
        from PIL import Image

        try:
            with Image.open(path) as image:
                # JPEG only: decode at a reduced scale that is still >= size (much faster, same result).
                image.draft(None, (self.size, self.size))
                image.load()
                rgb = self._as_rgb(image, path)
                # One resampling pass over the crop box: the same as resizing the shorter side and
                # cropping afterwards, without rounding twice.  Pillow's resize antialiases.
                square = rgb.resize((self.size, self.size), Image.Resampling.BICUBIC,
                                    box=crop_box(rgb.width, rgb.height, self.crop))
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
        if mode in _GREYSCALE_MODES:
            if not self.allow_greyscale:
                raise DatasetError(f"image {path} is greyscale (mode {mode}); set allow_greyscale=true to "
                                   f"copy it into 3 channels")
            return self._drop_opaque_alpha(image, path) if "A" in mode or "a" in mode else image.convert("RGB")
        if mode not in _COLOUR_MODES:
            raise DatasetError(f"image {path} has unsupported mode {mode}; expected 8-bit RGB")
        if mode == "P":
            # A palette image may mark one entry transparent; only then does it carry alpha.
            return self._drop_opaque_alpha(image.convert("RGBA"), path) if "transparency" in image.info \
                else image.convert("RGB")
        if mode in {"RGBA", "RGBa", "PA"}:
            return self._drop_opaque_alpha(image, path)
        return image.convert("RGB")

    def _drop_opaque_alpha(self, image: Any, path: Path) -> Any:
        alpha = image.getchannel(image.getbands()[-1])
        lowest, _ = alpha.getextrema()
        if lowest < 255:
            raise DatasetError(f"image {path} has transparent pixels (mode {image.mode}, alpha down to {lowest}); "
                               f"expected an opaque RGB image")
        return image.convert("RGB")


def read_image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image from its header, without decoding the pixels."""
    from PIL import Image

    try:
        with Image.open(path) as image:
            return image.size
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as exc:
        raise DatasetError(f"cannot read image header {path}: {type(exc).__name__}: {exc}") from None


# --------------------------------------------------------------------------------------------
# Records and the dataset
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class SampleRecord:
    """Where one sample's files are and what it is labelled; images are decoded later.

    Paths are strings relative to the dataset's base folder (or absolute): millions of records
    stay small.  ``reference`` is a no-contact frame of the same sensor, used only when the
    dataset subtracts it.
    """

    id: str
    tactile: str
    visual: str | None = None
    reference: str | None = None
    label: int = -1
    text: str = ""


def collect_records(candidates: Iterable[SampleRecord], *, config: ReaderConfig, skips: SkipLog, base: Path,
                    loader: ImageLoader, use_reference: bool, listed_in: str,
                    total: int | None = None) -> list[SampleRecord]:
    """Keep the usable candidate records, in order, up to ``max_samples``.

    Lenient builds decode every image of each candidate once so that corrupt files are skipped
    now rather than failing later.  Raises DatasetError when nothing is left (naming
    ``listed_in``) and otherwise warns once about what was skipped.
    """
    verify = _verifier(loader, base, use_reference) if config.lenient else None
    stage = "verifying images" if verify else "indexing"
    kept: list[SampleRecord] = []
    for record in progress(candidates, total=total, desc=f"{config.name}: {stage}", unit="sample"):
        problem = verify(record) if verify else None
        if problem:
            skips.reject(problem)
            continue
        kept.append(record)
        if config.max_samples is not None and len(kept) >= config.max_samples:
            break
    if not kept:
        if skips.reasons:
            raise DatasetError(f"{config.name}: no usable samples in {listed_in}; {skips.summary()}")
        raise DatasetError(f"{config.name}: the split is empty: {listed_in} lists no samples")
    skips.warn_if_any()
    return kept


def _verifier(loader: ImageLoader, base: Path, use_reference: bool) -> Callable[[SampleRecord], str | None]:
    def first_problem(record: SampleRecord) -> str | None:
        paths = [record.tactile, record.visual, record.reference if use_reference else None]
        for relative in paths:
            if relative is not None:
                problem = loader.problem(base / relative)
                if problem:
                    return f"sample {record.id}: {problem}"
        return None
    return first_problem


class RecordDataset(TactileDataset):
    """A dataset of indexed :class:`SampleRecord` s whose images are decoded on access.

    With ``subtract_reference`` the tactile image becomes ``tactile - reference + 0.5``,
    clamped to [0, 1], which keeps only what contact changed.
    """

    def __init__(self, records: Sequence[SampleRecord], *, base: Path, loader: ImageLoader, sensor: str,
                 class_names: Sequence[str] = (), subtract_reference: bool = False) -> None:
        has_visual = {record.visual is not None for record in records}
        if len(has_visual) > 1:
            raise ValueError("records must either all pair a visual image or none")
        if subtract_reference and any(record.reference is None for record in records):
            raise ValueError("subtract_reference needs a reference frame on every record")
        self.records: tuple[SampleRecord, ...] = tuple(records)
        self.base = base
        self.loader = loader
        self.sensor = sensor
        self.class_names = list(class_names)
        self.subtract_reference = subtract_reference
        self.has_visual = has_visual == {True}
        self._reference_cache: dict[str, torch.Tensor] = {}

    def __len__(self) -> int:
        return len(self.records)

    def __getitem__(self, index: int) -> dict[str, Any]:
        record = self.records[index]
        sample: dict[str, Any] = {"tactile": self._tactile(record), "label": record.label, "text": record.text,
                                  "sensor": self.sensor, "id": record.id}
        if record.visual is not None:
            sample["visual"] = self.loader.load(self.base / record.visual)
        return sample

    def _tactile(self, record: SampleRecord) -> torch.Tensor:
        tactile = self.loader.load(self.base / record.tactile)
        if not self.subtract_reference:
            return tactile
        assert record.reference is not None  # guaranteed by __init__
        return (tactile - self._reference(record.reference) + 0.5).clamp_(0.0, 1.0)

    def _reference(self, relative: str) -> torch.Tensor:
        cached = self._reference_cache.get(relative)
        if cached is None:
            if len(self._reference_cache) >= REFERENCE_CACHE_SIZE:
                self._reference_cache.clear()
            cached = self._reference_cache[relative] = self.loader.load(self.base / relative)
        return cached

    def __getstate__(self) -> dict[str, Any]:
        # DataLoader workers get their own cache rather than a pickled copy.
        return {**self.__dict__, "_reference_cache": {}}

    def __repr__(self) -> str:
        return (f"{type(self).__name__}({len(self)} samples, base={str(self.base)!r}, sensor={self.sensor!r}, "
                f"classes={self.num_classes}, visual={self.has_visual})")


def with_context_size(config: ReaderConfig, context: Any) -> ReaderConfig:
    """The config with ``image_size`` filled from the experiment's build context when unset."""
    return config if config.image_size else config.model_copy(update={"image_size": context.image_size})


def loader_for(config: ReaderConfig) -> ImageLoader:
    """The image loader that a reader config asks for."""
    return ImageLoader(size=config.image_size, crop=config.crop, allow_greyscale=config.allow_greyscale)


def relative_posix(path: Path, base: Path) -> str:
    """``path`` relative to ``base`` with forward slashes (stable sample ids across systems)."""
    return path.relative_to(base).as_posix()


"""Shared machinery of the dataset readers: image decoding, file checks, skipping (their shared options,
:class:`ReaderConfig`, are in :mod:`._options`, which imports no torch).

Every reader follows the same plan, implemented once here:

1. check the root folder and the dataset's own list/CSV files (:func:`require_root`,
   :func:`require_file`, :func:`read_list_lines`, :func:`read_csv_rows`, :func:`read_json`);
2. turn each listed entry into a :class:`SampleRecord` (paths, label, text, id), checking that
   its files exist with :class:`FileIndex` and reporting bad entries to a :class:`SkipLog`,
   which raises :class:`~vqtouch.core.DatasetError` in strict mode and records the reason when
   ``lenient`` is set;
3. :func:`collect_records` keeps the good records, applies ``max_samples``, refuses an empty
   split and emits the single warning that counts what was skipped.  It opens the header of every
   image of the kept records (:class:`~._headers.ImageCheck`: readable, an image, a supported mode,
   a single frame), so a strict build fails in its first seconds naming the bad file rather than
   mid-training;
   lenient builds also decode every image, so truncated files are skipped too.  Headers already
   read are remembered by file stat in a small JSON file under the user cache folder
   (:class:`~._headers.HeaderCache`), so building the same dataset again reads none of them;
4. :class:`RecordDataset` decodes images on access with :class:`ImageLoader`.

Pillow is imported inside the functions that decode, so importing a reader stays cheap.
"""

from __future__ import annotations

import csv
import json
import os
import re
import warnings
from collections import deque
from collections.abc import Iterable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from itertools import islice
from pathlib import Path
from typing import Any

import torch

from vqtouch.core import DatasetError, TactileDataset
from vqtouch.core.errors import VqtouchWarning
from vqtouch.plugins.utils.images import CropMode, ImageLoader, crop_box, mode_problem  # noqa: F401 - re-exported
from vqtouch.plugins.utils.progress import progress

from ._headers import HeaderCache, ImageCheck
from ._options import ReaderConfig

IMAGE_SUFFIXES = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".webp", ".tif", ".tiff"})

# Reasons quoted in the lenient-mode warning; the count covers the rest.
REASONS_SHOWN = 3
# Reference frames repeat across many samples (one per recording or trajectory).
REFERENCE_CACHE_SIZE = 64
# Header checks run in threads: on network storage each open waits mostly on the server.
HEADER_THREADS = 8
# Most candidates whose files are checked ahead of the one being judged (lists run to millions).
HEADER_WINDOW = 256
# Candidates checked per thread task: one task per file would cost more than a cached check.
HEADER_BATCH = 32


class SkippedSamplesWarning(VqtouchWarning):
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
        raise DatasetError(
            f"dataset {config.name!r} needs its folder: set dataset.root=/path/to/data (expected layout: {layout})"
        )
    root = Path(config.root).expanduser()
    if not root.is_dir():
        raise DatasetError(
            f"{config.name}: root folder {root} does not exist or is not a folder (expected layout: {layout})"
        )
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
    """Whether ``path`` names a visible file, or symbolic link, with a known image suffix.

    A broken link counts, so that the image check reports it instead of the sample vanishing.
    """
    return (
        path.suffix.lower() in IMAGE_SUFFIXES
        and not path.name.startswith(".")
        and (path.is_file() or path.is_symlink())
    )


def list_images(folder: Path, *, recursive: bool = False) -> list[Path]:
    """Image files in ``folder`` (optionally its sub-folders), in natural order of their relative paths."""
    candidates = folder.rglob("*") if recursive else folder.iterdir()
    images = [path for path in candidates if is_image_file(path)]
    return sorted(images, key=lambda path: natural_key(path.relative_to(folder).as_posix()))


def visible_subfolders(folder: Path) -> list[Path]:
    """Sub-folders of ``folder`` whose names do not start with a dot, sorted by name."""
    return sorted(
        (path for path in folder.iterdir() if path.is_dir() and not path.name.startswith(".")),
        key=lambda path: path.name,
    )


class FileIndex:
    """Answers "does this file exist?" from one directory listing per folder.

    Lists name up to hundreds of thousands of frames spread over a few hundred folders: one
    ``scandir`` per folder is far cheaper than one ``stat`` per file on network storage.  A
    symbolic link counts as existing even when broken, so that the image check reports it as a
    broken link (naming its target) rather than as a missing file.
    """

    def __init__(self) -> None:
        self._names_by_folder: dict[Path, frozenset[str]] = {}

    def exists(self, path: Path) -> bool:
        """Whether ``path`` is an existing file or a symbolic link (possibly broken)."""
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
                return frozenset(entry.name for entry in entries if entry.is_file() or entry.is_symlink())
        except (FileNotFoundError, NotADirectoryError):
            return frozenset()
        except OSError as exc:
            raise DatasetError(f"cannot list folder {folder}: {exc}") from None


# --------------------------------------------------------------------------------------------
# Images
# --------------------------------------------------------------------------------------------
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
    dataset subtracts it.  ``group`` names the recording (trial, fabric, ...) the sample belongs
    to, which a train/held-out split keeps on one side; None: the sample is a group of its own.
    """

    id: str
    tactile: str
    visual: str | None = None
    reference: str | None = None
    label: int = -1
    text: str = ""
    group: str | None = None


def collect_records(
    candidates: Iterable[SampleRecord],
    *,
    config: ReaderConfig,
    skips: SkipLog,
    base: Path,
    loader: ImageLoader,
    use_reference: bool,
    listed_in: str,
    total: int | None = None,
) -> list[SampleRecord]:
    """Keep the usable candidate records, in order, up to ``max_samples``.

    Every image of a record (its reference too with ``use_reference``) is checked with
    :class:`~._headers.ImageCheck` before the record is kept: headers always, pixels too when lenient, so
    bad files are found now rather than mid-training.  Checks run in threads a little ahead of
    the record being judged, never reading past what ``max_samples`` could keep.  Raises
    DatasetError when nothing is left (naming ``listed_in``) and otherwise warns once about what
    was skipped.
    """
    check = ImageCheck(
        base, loader, decode=config.lenient, cache=HeaderCache.open(base) if config.header_cache else None
    )
    stage = "verifying images" if config.lenient else "checking image headers"
    pulled = iter(progress(candidates, total=total, desc=f"{config.name}: {stage}", unit="sample"))
    pending: deque[tuple[list[SampleRecord], Future[list[str | None]]]] = deque()
    in_flight = 0
    kept: list[SampleRecord] = []
    pool = ThreadPoolExecutor(max_workers=HEADER_THREADS, thread_name_prefix="vqtouch-image-check")
    try:
        while True:
            # Read no further ahead than could still be kept: like a plain walk, a build stopped by
            # max_samples never reports problems in the lines after the samples it keeps.
            room = HEADER_WINDOW if config.max_samples is None else min(HEADER_WINDOW, config.max_samples - len(kept))
            while in_flight < room:
                batch = list(islice(pulled, min(HEADER_BATCH, room - in_flight)))
                if not batch:
                    break
                pending.append((batch, pool.submit(check.first_problems, batch, use_reference)))
                in_flight += len(batch)
            if not pending:
                break
            batch, problems = pending.popleft()
            in_flight -= len(batch)
            for record, problem in zip(batch, problems.result()):
                if problem:
                    skips.reject(problem)
                else:
                    kept.append(record)
            if config.max_samples is not None and len(kept) >= config.max_samples:
                break
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
        check.save()  # also after a strict failure: the good headers need not be read again
    if not kept:
        if skips.reasons:
            raise DatasetError(f"{config.name}: no usable samples in {listed_in}; {skips.summary()}")
        raise DatasetError(f"{config.name}: the split is empty: {listed_in} lists no samples")
    skips.warn_if_any()
    return kept


class RecordDataset(TactileDataset):
    """A dataset of indexed :class:`SampleRecord` s whose images are decoded on access.

    With ``subtract_reference`` the tactile image becomes ``tactile - reference + 0.5``,
    clamped to [0, 1], which keeps only what contact changed.  The records' ``group`` s are the
    dataset's split groups, each a ``split_unit`` ("recording", ...); without any, every sample
    is its own group.
    """

    def __init__(
        self,
        records: Sequence[SampleRecord],
        *,
        base: Path,
        loader: ImageLoader,
        sensor: str,
        class_names: Sequence[str] = (),
        subtract_reference: bool = False,
        split_unit: str | None = None,
    ) -> None:
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
        self._grouped = any(record.group is not None for record in self.records)
        if self._grouped:
            self.split_unit = split_unit or "group"

    def split_groups(self) -> list[str] | None:
        """Each record's ``group`` (a record without one is a group of its own, keyed by its id), or
        None when no record has a group."""
        if not self._grouped:
            return None
        # Ids are relative paths and group keys are folder names or column values: keep the two apart.
        return [record.group if record.group is not None else f"sample:{record.id}" for record in self.records]

    def __len__(self) -> int:
        return len(self.records)

    def __getitem__(self, index: int) -> dict[str, Any]:
        record = self.records[index]
        sample: dict[str, Any] = {
            "tactile": self._tactile(record),
            "label": record.label,
            "text": record.text,
            "sensor": self.sensor,
            "id": record.id,
        }
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
        return (
            f"{type(self).__name__}({len(self)} samples, base={str(self.base)!r}, sensor={self.sensor!r}, "
            f"classes={self.num_classes}, visual={self.has_visual})"
        )


def with_context_size(config: ReaderConfig, context: Any) -> ReaderConfig:
    """The config with ``image_size`` filled from the experiment's build context when unset."""
    return config if config.image_size else config.model_copy(update={"image_size": context.image_size})


def loader_for(config: ReaderConfig) -> ImageLoader:
    """The image loader that a reader config asks for."""
    return ImageLoader(size=config.image_size, crop=config.crop, allow_greyscale=config.allow_greyscale)


def relative_posix(path: Path, base: Path) -> str:
    """``path`` relative to ``base`` with forward slashes (stable sample ids across systems)."""
    return path.relative_to(base).as_posix()

"""The header check of the dataset readers (:mod:`._io`): every image of a reader's kept records is
opened, not decoded, when the reader is built (:class:`ImageCheck`), and the headers already read
are remembered by file stat under the user cache folder (:class:`HeaderCache`)."""

from __future__ import annotations

import hashlib
import json
import os
import stat
import tempfile
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from vqtouch.core import DatasetError
from vqtouch.plugins.utils.images import ImageLoader, mode_problem
from vqtouch.plugins.utils.splits import user_cache_folder

if TYPE_CHECKING:
    from ._io import SampleRecord

# Results of recent checks, so a reference frame shared by many samples is checked once.
CHECKED_MEMO_SIZE = 4096
# A file changed less than this long before its check is not cached: a second change within the
# same tick of the file system's clock would leave its stat unchanged (git's "racily clean" case).
HEADER_CACHE_SETTLE_NS = 2_000_000_000
HEADER_CACHE_VERSION = 1
# Formats whose extra frames are not an animation: a camera's multi-picture JPEG holds the photo
# first and previews after it, and Pillow reads the photo.
STILL_MULTI_FRAME_FORMATS = frozenset({"MPO"})


# --------------------------------------------------------------------------------------------
# Header check: every image opened, not decoded, when a reader is built
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class ImageHeader:
    """What Pillow reads from an image file without decoding its pixels."""

    format: str
    mode: str
    width: int
    height: int
    frames: int


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())


def _unopenable(path: Path, exc: BaseException) -> str:
    """Why ``path`` could not be opened, naming a broken link's target."""
    if isinstance(exc, FileNotFoundError) and os.path.islink(path):
        return f"image {path} is a broken symbolic link to {os.readlink(path)}; fix or remove it"
    if isinstance(exc, FileNotFoundError):
        return f"missing image {path}"
    return f"cannot read image {path}: {type(exc).__name__}: {_one_line(exc)}; replace or remove it"


def read_header(path: Path) -> ImageHeader:
    """The header of the image at ``path``; a DatasetError naming the file when it cannot be read."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as image:
            # n_frames walks the frame headers of GIF, PNG and TIFF files; no pixels are decoded.
            return ImageHeader(
                image.format or "unknown", image.mode, image.width, image.height, int(getattr(image, "n_frames", 1))
            )
    except UnidentifiedImageError:
        raise DatasetError(
            f"cannot read image {path}: not an image file Pillow can read; replace or remove it"
        ) from None
    except Exception as exc:  # noqa: BLE001 - damaged headers raise many types; each becomes a named bad file
        raise DatasetError(_unopenable(path, exc)) from None


def header_problem(header: ImageHeader, path: Path, allow_greyscale: bool) -> str | None:
    """Why an image with this header cannot be loaded, or None (transparency needs the pixels)."""
    if header.frames > 1 and header.format not in STILL_MULTI_FRAME_FORMATS:
        return (
            f"image {path} has {header.frames} frames ({header.format}); expected a single still image: "
            f"save one frame of it"
        )
    return mode_problem(path, header.mode, allow_greyscale)


class HeaderCache:
    """Image headers already read below one folder, remembered by file stat in a JSON file.

    An entry is used only while the file's size, modification and change times (nanoseconds)
    are those recorded, so a changed file is always read again; the change time also moves when
    a file is replaced keeping its size and modification time (``cp -p``, ``rsync -t``).  Files
    changed within :data:`HEADER_CACHE_SETTLE_NS` of their check are not recorded (see there).
    Only good headers are recorded: a bad file is opened again on every build, so its error is
    never stale.  The file is replaced atomically; concurrent builds (one per DDP rank) each write
    a complete file and the last one wins.  The cache is only a speed-up: a cache file that cannot
    be read is ignored and one that cannot be written is skipped, silently.
    """

    def __init__(self, base: Path, path: Path | None) -> None:
        self.base = os.path.abspath(base)
        self.path = path
        self._entries: dict[str, list[Any]] = {}
        self._changed = False
        self._lock = threading.Lock()

    @classmethod
    def open(cls, base: Path) -> HeaderCache:
        """The cache of the images below ``base``, loaded from the user cache folder if there."""
        folder = user_cache_folder()
        digest = hashlib.sha256(os.path.abspath(base).encode("utf-8", "surrogateescape")).hexdigest()[:32]
        cache = cls(base, folder / "image_headers" / f"{digest}.json" if folder else None)
        cache._load()
        return cache

    def lookup(self, key: str, status: os.stat_result) -> ImageHeader | None:
        """The recorded header of file ``key`` if its stat is unchanged, else None."""
        entry = self._entries.get(key)
        # Entries come from a file anyone can edit: use only well-formed ones.
        if (
            not isinstance(entry, list)
            or len(entry) != 8
            or entry[:3] != _stat_signature(status)
            or not all(isinstance(value, str) for value in entry[3:5])
            or not all(type(value) is int for value in entry[5:])
        ):
            return None
        return ImageHeader(*entry[3:])

    def store(self, key: str, status: os.stat_result, header: ImageHeader) -> None:
        """Record the header of file ``key`` read with stat ``status``, unless it changed too recently."""
        if time.time_ns() - max(status.st_mtime_ns, status.st_ctime_ns) < HEADER_CACHE_SETTLE_NS:
            return
        entry = [*_stat_signature(status), header.format, header.mode, header.width, header.height, header.frames]
        with self._lock:
            self._entries[key] = entry
            self._changed = True

    def forget(self, key: str) -> None:
        """Drop the record of file ``key`` (it is bad now)."""
        with self._lock:
            if self._entries.pop(key, None) is not None:
                self._changed = True

    def save(self) -> None:
        """Write the records if any changed: a temporary file in the same folder, then renamed over."""
        if not self._changed or self.path is None:
            return
        with self._lock:
            text = json.dumps(
                {"version": HEADER_CACHE_VERSION, "base": self.base, "files": self._entries}, separators=(",", ":")
            )
        temporary = None
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            handle, temporary = tempfile.mkstemp(dir=self.path.parent, prefix=f".{self.path.stem}.", suffix=".tmp")
            with os.fdopen(handle, "w", encoding="utf-8") as stream:
                stream.write(text)
                stream.flush()
                os.fsync(stream.fileno())  # the rename must not land before the data (a crash leaves the old file)
            os.replace(temporary, self.path)
            temporary = None
            self._changed = False
        except OSError:
            pass  # read-only or full cache folder: the next build reads the headers again
        finally:
            if temporary is not None:
                try:
                    os.unlink(temporary)
                except OSError:
                    pass

    def _load(self) -> None:
        if self.path is None:
            return
        try:
            data = json.loads(self.path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return  # absent, unreadable or damaged: start afresh and overwrite it
        if (
            isinstance(data, dict)
            and data.get("version") == HEADER_CACHE_VERSION
            and data.get("base") == self.base
            and isinstance(data.get("files"), dict)
        ):
            self._entries = data["files"]


def _stat_signature(status: os.stat_result) -> list[int]:
    return [status.st_size, status.st_mtime_ns, status.st_ctime_ns]


class ImageCheck:
    """Finds what is wrong with one image file of a dataset when the reader is built.

    Opens the header (readable, an image, a supported mode, a single frame) and, with
    ``decode``, decodes the pixels too (truncated data, transparency).  Paths are relative to
    ``base``; results of recent checks are kept so that shared reference frames are checked once.
    """

    def __init__(self, base: Path, loader: ImageLoader, *, decode: bool, cache: HeaderCache | None) -> None:
        self.base = base
        self.loader = loader
        self.decode = decode
        self.cache = cache
        self._recent: dict[str, str | None] = {}

    def problem(self, relative: str) -> str | None:
        """Why image ``relative`` cannot be used, or None."""
        if relative in self._recent:
            return self._recent[relative]
        path = self.base / relative
        try:
            header = self._header(relative, path)
        except DatasetError as exc:
            problem: str | None = str(exc)
        else:
            problem = header_problem(header, path, self.loader.allow_greyscale)
            if problem is None and self.decode:
                problem = self.loader.problem(path)
        if len(self._recent) >= CHECKED_MEMO_SIZE:
            self._recent.clear()
        self._recent[relative] = problem
        return problem

    def _header(self, relative: str, path: Path) -> ImageHeader:
        if self.cache is None:
            return read_header(path)
        try:
            status = os.stat(path)
            if not stat.S_ISREG(status.st_mode):
                raise DatasetError(f"image {path} is not a file; replace or remove it")
            cached = self.cache.lookup(relative, status)
            header = cached or read_header(path)
        except OSError as exc:
            self.cache.forget(relative)
            raise DatasetError(_unopenable(path, exc)) from None
        except DatasetError:
            self.cache.forget(relative)
            raise
        if cached is None:
            self.cache.store(relative, status, header)
        return header

    def first_problems(self, records: Sequence[SampleRecord], use_reference: bool) -> list[str | None]:
        """For each record, the first problem among its images (reference included if used), or None."""
        found = []
        for record in records:
            paths = (record.tactile, record.visual, record.reference if use_reference else None)
            problem = next((problem for path in paths if path is not None and (problem := self.problem(path))), None)
            found.append(f"sample {record.id}: {problem}" if problem else None)
        return found

    def save(self) -> None:
        """Write the header cache, if there is one."""
        if self.cache is not None:
            self.cache.save()

"""Generic reader for tactile images in class folders or listed in a CSV.

Two layouts:

- class folders (``csv`` empty): ``<root>/<class>/**/<image>``; class names are the sorted
  sub-folder names (plain string order) unless ``class_names`` fixes them; images directly in
  ``<root>`` belong to no class and are bad samples;
- a CSV (``csv`` set) whose header has ``path`` and ``label`` and optionally ``visual``,
  ``text`` and ``group`` (any column order; other columns, such as those ``vqtouch data
  render`` adds, are ignored).  Paths are relative to the CSV's folder.  A label is a class name or an integer
  index; an empty label or -1 means "no label".  Without ``class_names``, integer labels give
  the classes "0".."max" and name labels the sorted distinct names; a column that mixes both is
  refused, since what the integers mean is then unknown (set ``class_names`` to say it).  With
  ``visual``, every row must name a visual image, which is returned as ``"visual"``.

Split groups (samples that ``split_dataset`` keeps on one side, e.g. the frames of one
recording): in a CSV, the optional ``group`` column (an empty cell: a group of its own); in class
folders, the sub-folder below the class folder (``<root>/<class>/<recording>/**/<image>``), while
an image directly in its class folder is a group of its own.  The class folder itself is never
the group: holding out whole classes would leave their labels untrained.
"""

from __future__ import annotations

import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from vqtouch.core import BuildContext, DatasetError
from vqtouch.plugins.data.readers._io import (
    with_context_size,
    FileIndex,
    RecordDataset,
    SampleRecord,
    SkipLog,
    collect_records,
    is_image_file,
    list_images,
    loader_for,
    read_csv_rows,
    relative_posix,
    require_file,
    require_root,
    resolve_under,
    visible_subfolders,
)

from .image_folder_plugin import READER, ImageFolderConfig

LAYOUT = "<root>/<class>/<image> (one sub-folder per class), or a CSV with header path,label[,visual]"
REQUIRED_COLUMNS = ("path", "label")
OPTIONAL_COLUMNS = ("visual", "text", "group")
UNLABELLED = -1
_INTEGER = re.compile(r"-?\d+")


class ImageFolderDataset(RecordDataset):
    """Images from class folders or a CSV, with an optional paired visual image and split groups
    (see the module docstring)."""


# --------------------------------------------------------------------------------------------
# Class folders
# --------------------------------------------------------------------------------------------
def _folder_candidates(
    root: Path, folders: Sequence[Path], label_of: dict[str, int], skips: SkipLog
) -> Iterator[SampleRecord]:
    for stray in (path for path in sorted(root.iterdir()) if is_image_file(path)):
        skips.reject(f"image {stray} is not inside a class sub-folder of {root}")
    for folder in folders:
        for image in list_images(folder, recursive=True):
            path = relative_posix(image, root)
            nested = image.relative_to(folder).parts[:-1]
            yield SampleRecord(
                id=path,
                tactile=path,
                label=label_of[folder.name],
                group=f"{folder.name}/{nested[0]}" if nested else None,
            )


def _build_from_folders(config: ImageFolderConfig, root: Path, skips: SkipLog) -> ImageFolderDataset:
    folders = visible_subfolders(root)
    if not folders:
        raise DatasetError(
            f"{READER}: no class sub-folders in {root}; put each class's images in <root>/<class>/ "
            f"or set csv=<file> to list them"
        )
    class_names = list(config.class_names) or [folder.name for folder in folders]
    unknown = [folder.name for folder in folders if folder.name not in class_names]
    if unknown:
        raise DatasetError(f"{READER}: sub-folder(s) {unknown} of {root} are not in class_names {class_names}")
    label_of = {name: label for label, name in enumerate(class_names)}
    loader = loader_for(config)
    records = collect_records(
        _folder_candidates(root, folders, label_of, skips),
        config=config,
        skips=skips,
        base=root,
        loader=loader,
        use_reference=False,
        listed_in=f"the class folders of {root}",
    )
    return ImageFolderDataset(
        records, base=root, loader=loader, sensor=config.sensor, class_names=class_names, split_unit="folder"
    )


# --------------------------------------------------------------------------------------------
# CSV
# --------------------------------------------------------------------------------------------
def _column_positions(header: list[str], csv_path: Path) -> dict[str, int]:
    names = [cell.lower() for cell in header]
    if len(set(names)) != len(names) or not set(REQUIRED_COLUMNS) <= set(names):
        raise DatasetError(
            f"{READER}: {csv_path}: header must name each column once and include path and label "
            f"(optionally visual, text, group); got {header}"
        )
    return {name: position for position, name in enumerate(names)}


@dataclass(frozen=True)
class LabelMap:
    """Maps a CSV label cell to a class index: None when the cell names no class."""

    names: tuple[str, ...]
    accepts_integers: bool
    _index_of: dict[str, int] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "_index_of", {name: label for label, name in enumerate(self.names)})

    def __call__(self, cell: str) -> int | None:
        if cell in ("", str(UNLABELLED)):
            return UNLABELLED
        if cell in self._index_of:
            return self._index_of[cell]
        if self.accepts_integers and _INTEGER.fullmatch(cell) and 0 <= int(cell) < len(self.names):
            return int(cell)
        return None


def label_map_for(cells: list[str], fixed: Sequence[str], csv_path: Path) -> LabelMap:
    """How the label column is read: by the fixed class names, as integers, or as names."""
    if fixed:
        return LabelMap(tuple(fixed), accepts_integers=True)
    given = [cell for cell in cells if cell not in ("", str(UNLABELLED))]
    integers = [int(cell) for cell in given if _INTEGER.fullmatch(cell)]
    if integers and len(integers) != len(given):
        raise DatasetError(
            f"{READER}: {csv_path}: the label column mixes integers and class names; set class_names "
            f"to say which class each integer means"
        )
    if integers:
        return LabelMap(tuple(str(label) for label in range(max(integers) + 1)), accepts_integers=True)
    return LabelMap(tuple(sorted(set(given))), accepts_integers=False)


def _csv_candidates(
    rows: list[tuple[int, list[str]]],
    columns: dict[str, int],
    csv_path: Path,
    label_of: LabelMap,
    skips: SkipLog,
    paths_outside: bool,
) -> Iterator[SampleRecord]:
    base, files = csv_path.parent, FileIndex()
    for number, cells in rows:
        where = f"{csv_path} line {number}"
        if len(cells) != len(columns):  # columns maps every header cell, used or not
            skips.reject(f"{where}: expected {len(columns)} columns, got {len(cells)}")
            continue
        tactile, label_cell = cells[columns["path"]], cells[columns["label"]]
        visual = cells[columns["visual"]] if "visual" in columns else None
        for path in (tactile, visual):
            if path and not paths_outside and not (base / path).resolve().is_relative_to(base.resolve()):
                raise DatasetError(
                    f"{READER}: {where}: {path!r} is outside {base}; list images inside the CSV's "
                    "folder, or set the reader's paths_outside=true to allow it"
                )
        text = cells[columns["text"]] if "text" in columns else ""
        group = cells[columns["group"]] if "group" in columns else ""
        label = label_of(label_cell)
        if label is None:
            skips.reject(f"{where}: label {label_cell!r} is not a valid class")
            continue
        wanted = [("image", tactile)] + ([("visual image", visual)] if visual is not None else [])
        problems = [
            f"{kind} is empty" if not path else f"missing {kind} {base / path}"
            for kind, path in wanted
            if not path or not files.exists(base / path)
        ]
        if problems:
            skips.reject(f"{where}: {' and '.join(problems)}")
            continue
        yield SampleRecord(
            id=Path(tactile).as_posix(), tactile=tactile, visual=visual, label=label, text=text, group=group or None
        )


def _build_from_csv(config: ImageFolderConfig, root: Path, skips: SkipLog) -> ImageFolderDataset:
    csv_path = require_file(resolve_under(config.csv, root), READER, "CSV list")
    rows = read_csv_rows(csv_path, READER)
    if not rows:
        raise DatasetError(f"{READER}: {csv_path} is empty; expected the header path,label[,visual]")
    columns = _column_positions(rows[0][1], csv_path)
    body = rows[1:]
    label_cells = [cells[columns["label"]] for _, cells in body if len(cells) == len(columns)]
    label_of = label_map_for(label_cells, config.class_names, csv_path)
    loader = loader_for(config)
    candidates = _csv_candidates(body, columns, csv_path, label_of, skips, config.paths_outside)
    records = collect_records(
        candidates,
        config=config,
        skips=skips,
        base=csv_path.parent,
        loader=loader,
        use_reference=False,
        listed_in=str(csv_path),
        total=len(body),
    )
    return ImageFolderDataset(
        records,
        base=csv_path.parent,
        loader=loader,
        sensor=config.sensor,
        class_names=label_of.names,
        split_unit="group",
    )


def build_image_folder(config: ImageFolderConfig, context: BuildContext) -> ImageFolderDataset:
    """Factory: read class folders, or the CSV when one is configured."""
    config = with_context_size(config, context)
    root = require_root(config, LAYOUT)
    skips = SkipLog(READER, config.lenient)
    return _build_from_csv(config, root, skips) if config.csv else _build_from_folders(config, root, skips)

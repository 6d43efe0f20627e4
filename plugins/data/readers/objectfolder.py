"""ObjectFolder readers: ObjectFolder-Real tactile recordings and the visuo-tactile cross-generation benchmark.

``objectfolder_real`` reads the layout that alanzjl/t3 and facebookresearch/sparsh walk::

    <root>/<obj_idx>/tactile_data/<trial_idx>/0/gelsight/*.png

Folders whose names are not integers are ignored, and only ``.png`` frames are read (T3's
pre-processing writes ``.jpg`` copies next to them).  Objects, trials and frames are taken in
natural order.  No list ships with the data, so this is the one reader that walks folders, all
of whose names are documented.  Labels come from T3's ``objectfolder_real_metadata.csv``
(columns Index, Name, Material): the class is the object's material, classes are the sorted
material names (as T3 numbers them); without the CSV every label is -1.  Paired vision frames
are not documented, so samples are tactile-only.

``objectfolder_cross`` reads the cross-generation benchmark (objectfolder/visuo-tactile-cross-generation)::

    <root>/vision/<obj>/<contact>.png, <root>/touch/<obj>/<contact>.png
    <root>/touch_ref/touch_ref.png                         no-contact tactile frame
    split JSON {"train": [[obj, contact], ...], "val": [...], "test": [...]}

The label is the object: classes are the objects named anywhere in the split JSON, in natural
order, so a label means the same object in every split (cross-object test objects included).

Split groups (what ``split_dataset`` holds out whole): for ObjectFolder-Real the trial
(``<obj_idx>/tactile_data/<trial_idx>/``), whose frames record one touch and are near-duplicates;
an object-level split is the ``objects`` option.  A cross-generation sample is one contact, so
each is its own group (the split JSON itself decides cross-contact or cross-object).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

from vqtouch.core import BuildContext, DatasetError
from vqtouch.plugins.data.readers._io import (
    with_context_size,
    FileIndex,
    RecordDataset,
    SampleRecord,
    SkipLog,
    collect_records,
    list_images,
    loader_for,
    natural_key,
    read_csv_rows,
    read_json,
    relative_posix,
    require_file,
    require_root,
    resolve_under,
    visible_subfolders,
)

from .objectfolder_plugin import CROSS, REAL, ObjectFolderCrossConfig, ObjectFolderRealConfig

REAL_LAYOUT = "<root>/<obj_idx>/tactile_data/<trial_idx>/0/gelsight/*.png"
CROSS_LAYOUT = "<root>/{vision,touch}/<obj>/<contact>.png, <root>/touch_ref/touch_ref.png and a split JSON"
METADATA_NAME = "objectfolder_real_metadata.csv"
METADATA_COLUMNS = ("index", "name", "material")
TOUCH_REFERENCE = "touch_ref/touch_ref.png"
SENSOR = "gelsight"


# --------------------------------------------------------------------------------------------
# ObjectFolder-Real
# --------------------------------------------------------------------------------------------
class ObjectFolderRealDataset(RecordDataset):
    """ObjectFolder-Real samples: one GelSight frame each, labelled by the object's material; split
    groups are trials (``<obj_idx>/<trial_idx>``)."""


def read_material_table(path: Path) -> dict[int, str]:
    """Material of each object index from T3's metadata CSV."""
    rows = read_csv_rows(path, REAL)
    if not rows:
        raise DatasetError(f"{REAL}: {path} is empty")
    header = [cell.lower() for cell in rows[0][1]]
    if not all(column in header for column in METADATA_COLUMNS):
        raise DatasetError(f"{REAL}: {path}: header must name the columns Index, Name, Material; got {rows[0][1]}")
    index_at, material_at = header.index("index"), header.index("material")
    materials: dict[int, str] = {}
    for number, cells in rows[1:]:
        try:
            object_index, material = int(cells[index_at]), cells[material_at]
        except (IndexError, ValueError):
            raise DatasetError(
                f"{REAL}: {path} line {number}: expected an integer Index and a Material, got {cells}"
            ) from None
        if object_index in materials or not material:
            problem = "repeats an Index" if object_index in materials else "has no Material"
            raise DatasetError(f"{REAL}: {path} line {number} {problem}")
        materials[object_index] = material
    return materials


def _metadata_path(config: ObjectFolderRealConfig, root: Path) -> Path | None:
    if config.metadata_csv:
        return require_file(resolve_under(config.metadata_csv, root), REAL, "metadata CSV")
    default = root / METADATA_NAME
    return default if default.is_file() else None


def _object_folders(config: ObjectFolderRealConfig, root: Path) -> list[tuple[int, Path]]:
    on_disk = {int(folder.name): folder for folder in visible_subfolders(root) if folder.name.isdigit()}
    if not config.objects:
        return sorted(on_disk.items())
    absent = [index for index in config.objects if index not in on_disk]
    if absent:
        raise DatasetError(f"{REAL}: no folder for object(s) {absent} under {root}")
    return [(index, on_disk[index]) for index in config.objects]


def _trial_frames(object_index: int, folder: Path, skips: SkipLog) -> Iterator[Path]:
    """The .png GelSight frames of one object, trial by trial, in natural order."""
    trials_folder = folder / "tactile_data"
    if not trials_folder.is_dir():
        skips.reject(f"object {object_index}: missing folder {trials_folder}")
        return
    trials = sorted(
        (trial for trial in visible_subfolders(trials_folder) if trial.name.isdigit()),
        key=lambda trial: int(trial.name),
    )
    for trial in trials:
        frames_folder = trial / "0" / "gelsight"
        if not frames_folder.is_dir():
            skips.reject(f"object {object_index} trial {trial.name}: missing folder {frames_folder}")
            continue
        yield from (frame for frame in list_images(frames_folder) if frame.suffix.lower() == ".png")


def _real_candidates(
    objects: list[tuple[int, Path]],
    root: Path,
    materials: dict[int, str] | None,
    class_names: list[str],
    metadata: Path | None,
    skips: SkipLog,
) -> Iterator[SampleRecord]:
    for object_index, folder in objects:
        label = -1
        if materials is not None:
            if object_index not in materials:
                # Counted for the warning only; problems inside an object skipped anyway are not reported.
                frames = sum(1 for _ in _trial_frames(object_index, folder, SkipLog(REAL, lenient=True)))
                skips.reject(f"object {object_index} ({folder}, {frames} frames) has no row in {metadata}", frames)
                continue
            label = class_names.index(materials[object_index])
        for frame in _trial_frames(object_index, folder, skips):
            path = relative_posix(frame, root)
            trial = frame.parents[2].name  # <trial_idx>/0/gelsight/<frame>
            yield SampleRecord(id=path, tactile=path, label=label, group=f"{object_index}/{trial}")


def build_objectfolder_real(config: ObjectFolderRealConfig, context: BuildContext) -> ObjectFolderRealDataset:
    """Factory: walk the documented object/trial folders and label frames by material."""
    config = with_context_size(config, context)
    root = require_root(config, REAL_LAYOUT)
    metadata = _metadata_path(config, root)
    materials = read_material_table(metadata) if metadata is not None else None
    class_names = sorted(set(materials.values())) if materials is not None else []
    skips = SkipLog(REAL, config.lenient)
    loader = loader_for(config)
    candidates = _real_candidates(_object_folders(config, root), root, materials, class_names, metadata, skips)
    records = collect_records(
        candidates,
        config=config,
        skips=skips,
        base=root,
        loader=loader,
        use_reference=False,
        listed_in=f"{root} (expected {REAL_LAYOUT})",
    )
    return ObjectFolderRealDataset(
        records, base=root, loader=loader, sensor=SENSOR, class_names=class_names, split_unit="trial"
    )


# --------------------------------------------------------------------------------------------
# Cross-generation benchmark
# --------------------------------------------------------------------------------------------
class ObjectFolderCrossDataset(RecordDataset):
    """Cross-generation samples: the touch and vision image of one (object, contact), labelled by object.
    No split groups: every sample is a contact of its own."""


def _is_key(value: Any) -> bool:
    return isinstance(value, (int, str)) and not isinstance(value, bool)


def _is_pair(entry: Any) -> bool:
    return isinstance(entry, list) and len(entry) == 2 and all(_is_key(value) for value in entry)


def _read_splits(path: Path, split: str) -> dict[str, list[Any]]:
    splits = read_json(path, CROSS)
    if not isinstance(splits, dict) or not all(isinstance(entries, list) for entries in splits.values()):
        raise DatasetError(f'{CROSS}: {path} must be an object of lists like {{"train": [[obj, contact], ...]}}')
    if split not in splits:
        raise DatasetError(f"{CROSS}: {path} has no {split!r} list (it has: {', '.join(sorted(splits)) or 'none'})")
    return splits


def _cross_candidates(
    entries: list[Any], where: str, root: Path, label_of: dict[str, int], check_reference: bool, skips: SkipLog
) -> Iterator[SampleRecord]:
    files = FileIndex()
    if check_reference and not files.exists(root / TOUCH_REFERENCE):
        raise DatasetError(f"{CROSS}: subtract_reference needs the no-contact frame {root / TOUCH_REFERENCE}")
    for position, entry in enumerate(entries):
        if not _is_pair(entry):
            skips.reject(f"{where}[{position}]: expected [object, contact], got {entry!r}")
            continue
        obj, contact = (str(value) for value in entry)
        tactile, visual = f"touch/{obj}/{contact}.png", f"vision/{obj}/{contact}.png"
        missing = [
            f"{kind} image {root / path}"
            for kind, path in (("touch", tactile), ("vision", visual))
            if not files.exists(root / path)
        ]
        if missing:
            skips.reject(f"{where}[{position}]: missing {' and '.join(missing)}")
            continue
        yield SampleRecord(id=tactile, tactile=tactile, visual=visual, reference=TOUCH_REFERENCE, label=label_of[obj])


def build_objectfolder_cross(config: ObjectFolderCrossConfig, context: BuildContext) -> ObjectFolderCrossDataset:
    """Factory: read one list of the split JSON and check every (object, contact) pair."""
    config = with_context_size(config, context)
    root = require_root(config, CROSS_LAYOUT)
    split_path = require_file(resolve_under(config.split_file, root), CROSS, "split JSON")
    splits = _read_splits(split_path, config.split)
    objects = sorted(
        {str(entry[0]) for entries in splits.values() for entry in entries if _is_pair(entry)}, key=natural_key
    )
    label_of = {obj: label for label, obj in enumerate(objects)}
    entries = splits[config.split]
    skips = SkipLog(CROSS, config.lenient)
    loader = loader_for(config)
    candidates = _cross_candidates(
        entries, f"{split_path} {config.split}", root, label_of, config.subtract_reference, skips
    )
    records = collect_records(
        candidates,
        config=config,
        skips=skips,
        base=root,
        loader=loader,
        use_reference=config.subtract_reference,
        listed_in=f"the {config.split!r} list of {split_path}",
        total=len(entries),
    )
    return ObjectFolderCrossDataset(
        records,
        base=root,
        loader=loader,
        sensor=SENSOR,
        class_names=objects,
        subtract_reference=config.subtract_reference,
    )

"""Touch and Go reader (Yang et al. 2022, fredfyyang/Touch-and-Go): GelSight frames paired with video frames.

Layout, as written by the repository's ``extract_frame.py`` and read by its ``dataset.py``::

    <root>/
      dataset/<YYYYMMDD_HHMMSS>/video_frame/<##########>.jpg     visual frame
      dataset/<YYYYMMDD_HHMMSS>/gelsight_frame/<##########>.jpg  tactile frame, same name = pair
      dataset/{train,test,pretrain,train_rough,test_rough}.txt   lines "<recording>/<frame>.jpg,<label>"
      label.txt                                                   the same format, every labelled frame
      category_reference.txt                                      lines "<Name>: <id>" (names may hold "(...)")

Labels:

- material lists (train, test, pretrain, label.txt): class ids and names come from
  ``category_reference.txt``; id -1 ("Inconclusive") is dropped, since such frames have no
  material (their count is kept in ``dropped_unlabelled``);
- ``labels="hard_soft"`` maps material ids {7, 8, 9, 11, 13} (leather, both fabrics, paper,
  grass) to "soft" and the rest to "hard", as the repository's ``dataset.py`` does;
- the rough lists carry binary labels whose meaning (which of 0/1 is rough) the repository
  does not document, so their classes are named ``rough_smooth_0`` and ``rough_smooth_1``.

Split groups: the recording folder (``dataset/<recording>/``).  Its frames are consecutive video
frames of one contact sequence, near-duplicates of each other, so ``split_dataset`` holds out
whole recordings.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator
from pathlib import Path

from vqtouch.core import BuildContext, DatasetError
from vqtouch.plugins.data.readers._io import (
    with_context_size,
    FileIndex,
    RecordDataset,
    SampleRecord,
    SkipLog,
    collect_records,
    loader_for,
    read_list_lines,
    require_file,
    require_folder,
    require_root,
)

from .touch_and_go_plugin import READER, ROUGH_SPLITS, TouchAndGoConfig

LAYOUT = (
    "<root>/dataset/<recording>/{video_frame,gelsight_frame}/<frame>.jpg, <root>/dataset/<split>.txt, "
    "<root>/label.txt, <root>/category_reference.txt"
)
SPLIT_LISTS = {
    "train": "dataset/train.txt",
    "test": "dataset/test.txt",
    "pretrain": "dataset/pretrain.txt",
    "train_rough": "dataset/train_rough.txt",
    "test_rough": "dataset/test_rough.txt",
    "all": "label.txt",
}
ROUGH_CLASS_NAMES = ("rough_smooth_0", "rough_smooth_1")
HARD_SOFT_CLASS_NAMES = ("hard", "soft")
SOFT_MATERIAL_IDS = frozenset({7, 8, 9, 11, 13})
UNLABELLED = -1

_LIST_LINE = re.compile(r"(?P<recording>[^/,\s]+)/(?P<frame>[^/,\s]+)\s*,\s*(?P<label>-?\d+)")
# Greedy name: everything up to the last colon, so names may contain ':' or '(...)'.
_CATEGORY_LINE = re.compile(r"(?P<name>.*\S)\s*:\s*(?P<id>-?\d+)")


class TouchAndGoDataset(RecordDataset):
    """Touch and Go samples: tactile = gelsight_frame, visual = video_frame of the same index."""

    def __init__(self, *args, dropped_unlabelled: int = 0, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        #: List lines with label -1 ("Inconclusive"), left out on purpose.
        self.dropped_unlabelled = dropped_unlabelled


def parse_category_reference(path: Path) -> list[str]:
    """Class names indexed by id from ``category_reference.txt`` (the -1 entry is left out)."""
    names_by_id: dict[int, str] = {}
    for number, line in read_list_lines(path, READER):
        match = _CATEGORY_LINE.fullmatch(line)
        if match is None:
            raise DatasetError(f"{READER}: {path} line {number}: expected '<Name>: <id>', got {line!r}")
        class_id = int(match["id"])
        if class_id == UNLABELLED:
            continue
        if class_id < 0 or class_id in names_by_id:
            problem = "negative" if class_id < 0 else f"already used by {names_by_id[class_id]!r}"
            raise DatasetError(f"{READER}: {path} line {number}: class id {class_id} is {problem}")
        names_by_id[class_id] = match["name"]
    if sorted(names_by_id) != list(range(len(names_by_id))):
        raise DatasetError(f"{READER}: {path}: class ids must be 0..K-1 without gaps; got {sorted(names_by_id)}")
    if not names_by_id:
        raise DatasetError(f"{READER}: {path} defines no classes")
    return [names_by_id[class_id] for class_id in range(len(names_by_id))]


def _label_scheme(config: TouchAndGoConfig, root: Path) -> tuple[list[str], Callable[[int], int | None], str]:
    """Class names, a map from list label to class index (None when out of range) and its source."""
    if config.split in ROUGH_SPLITS:
        return list(ROUGH_CLASS_NAMES), lambda raw: raw if raw in (0, 1) else None, "the rough/smooth labels {0, 1}"
    reference = require_file(root / "category_reference.txt", READER, "class list category_reference.txt")
    materials = parse_category_reference(reference)
    source = f"{reference} (ids 0..{len(materials) - 1})"
    if config.labels == "hard_soft":
        return (
            list(HARD_SOFT_CLASS_NAMES),
            lambda raw: int(raw in SOFT_MATERIAL_IDS) if 0 <= raw < len(materials) else None,
            source,
        )
    return materials, lambda raw: raw if 0 <= raw < len(materials) else None, source


def _candidates(
    lines: list[tuple[int, str]],
    list_name: str,
    root: Path,
    label_of: Callable[[int], int | None],
    label_source: str,
    skips: SkipLog,
) -> Iterator[SampleRecord]:
    files = FileIndex()
    for number, line in lines:
        where = f"{list_name} line {number}"
        match = _LIST_LINE.fullmatch(line)
        if match is None:
            skips.reject(f"{where}: expected '<recording>/<frame>.jpg,<label>', got {line!r}")
            continue
        raw_label = int(match["label"])
        if raw_label == UNLABELLED:
            continue
        label = label_of(raw_label)
        if label is None:
            skips.reject(f"{where}: label {raw_label} is not a class of {label_source}")
            continue
        recording, frame = match["recording"], match["frame"]
        tactile = f"dataset/{recording}/gelsight_frame/{frame}"
        visual = f"dataset/{recording}/video_frame/{frame}"
        missing = [
            f"{kind} frame {root / path}"
            for kind, path in (("tactile", tactile), ("visual", visual))
            if not files.exists(root / path)
        ]
        if missing:
            skips.reject(f"{where}: missing {' and '.join(missing)}")
            continue
        yield SampleRecord(id=f"{recording}/{frame}", tactile=tactile, visual=visual, label=label, group=recording)


def build_touch_and_go(config: TouchAndGoConfig, context: BuildContext) -> TouchAndGoDataset:
    """Factory: index the chosen list, checking every frame pair and label."""
    config = with_context_size(config, context)
    root = require_root(config, LAYOUT)
    require_folder(root / "dataset", READER, "frames (dataset/<recording>/...)")
    list_path = require_file(root / SPLIT_LISTS[config.split], READER, f"{config.split!r} list")
    class_names, label_of, label_source = _label_scheme(config, root)
    lines = read_list_lines(list_path, READER)
    dropped = sum(1 for _, line in lines if (match := _LIST_LINE.fullmatch(line)) and int(match["label"]) == UNLABELLED)
    skips = SkipLog(READER, config.lenient)
    loader = loader_for(config)
    candidates = _candidates(lines, str(list_path), root, label_of, label_source, skips)
    records = collect_records(
        candidates,
        config=config,
        skips=skips,
        base=root,
        loader=loader,
        use_reference=False,
        listed_in=str(list_path),
        total=len(lines),
    )
    return TouchAndGoDataset(
        records,
        base=root,
        loader=loader,
        sensor="gelsight",
        class_names=class_names,
        dropped_unlabelled=dropped,
        split_unit="recording",
    )

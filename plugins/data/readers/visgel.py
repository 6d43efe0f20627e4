"""VisGel reader (Li et al. 2019, YunzhuLi/VisGel): GelSight frames paired with camera frames.

The dataset ships list files, read here as they are; the folder names inside ``data_seen/`` and
``data_unseen/`` are not documented, so nothing below the lists is guessed::

    <root>/
      data_lst/{train,eval,demo}_{vision2touch,touch2vision}.txt
      data_seen/..., data_unseen/...        whatever the lists name, relative to <root>

Each list line holds 8 space-separated paths ``ref_src ref_des src des src_pre_0 src_pre_1
src_nxt_0 src_nxt_1``: ``src`` is the input modality of the list's direction and ``des`` the
output, ``ref_*`` the no-contact frames of the same recording.  For ``vision2touch`` lists the
visual image is ``src`` and the tactile image ``des`` (tactile reference ``ref_des``); for
``touch2vision`` lists it is the other way round (tactile ``src``, reference ``ref_src``).  The
time-window neighbours are not used.  VisGel has no labels or text.

Split groups: the recording, known by its no-contact reference frame (``ref_src``/``ref_des``
are the reference frames of the recording a line's frames come from): lines sharing the tactile
reference frame are frames of one recording, and ``split_dataset`` holds out whole recordings.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from vqtouch.core import BuildContext
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
    require_root,
)

from .visgel_plugin import READER, VisGelConfig

LAYOUT = "<root>/data_lst/<split>_<direction>.txt with 8 space-separated paths per line, relative to <root>"
PATHS_PER_LINE = 8
# Positions within a list line.
REF_SRC, REF_DES, SRC, DES = 0, 1, 2, 3


class VisGelDataset(RecordDataset):
    """VisGel samples: the tactile and visual frames of one list line (no labels)."""


def _columns(direction: str) -> tuple[int, int, int]:
    """Positions of (visual, tactile, tactile reference) in a line of the ``direction`` lists."""
    if direction == "vision2touch":
        return SRC, DES, REF_DES
    return DES, SRC, REF_SRC


def _candidates(
    lines: list[tuple[int, str]], list_name: str, root: Path, direction: str, check_reference: bool, skips: SkipLog
) -> Iterator[SampleRecord]:
    files = FileIndex()
    visual_at, tactile_at, reference_at = _columns(direction)
    for number, line in lines:
        where = f"{list_name} line {number}"
        paths = line.split()
        if len(paths) != PATHS_PER_LINE:
            skips.reject(f"{where}: expected {PATHS_PER_LINE} space-separated paths, got {len(paths)}")
            continue
        wanted = [("visual", paths[visual_at]), ("tactile", paths[tactile_at])]
        if check_reference:
            wanted.append(("tactile reference", paths[reference_at]))
        missing = [f"{kind} frame {root / path}" for kind, path in wanted if not files.exists(root / path)]
        if missing:
            skips.reject(f"{where}: missing {' and '.join(missing)}")
            continue
        yield SampleRecord(
            id=paths[tactile_at],
            tactile=paths[tactile_at],
            visual=paths[visual_at],
            reference=paths[reference_at],
            group=paths[reference_at],
        )


def build_visgel(config: VisGelConfig, context: BuildContext) -> VisGelDataset:
    """Factory: index one VisGel list, checking that every frame it names exists."""
    config = with_context_size(config, context)
    root = require_root(config, LAYOUT)
    list_path = require_file(
        root / "data_lst" / f"{config.split}_{config.direction}.txt", READER, f"{config.split} {config.direction} list"
    )
    lines = read_list_lines(list_path, READER)
    skips = SkipLog(READER, config.lenient)
    loader = loader_for(config)
    candidates = _candidates(lines, str(list_path), root, config.direction, config.subtract_reference, skips)
    records = collect_records(
        candidates,
        config=config,
        skips=skips,
        base=root,
        loader=loader,
        use_reference=config.subtract_reference,
        listed_in=str(list_path),
        total=len(lines),
    )
    return VisGelDataset(
        records,
        base=root,
        loader=loader,
        sensor="gelsight",
        subtract_reference=config.subtract_reference,
        split_unit="recording",
    )

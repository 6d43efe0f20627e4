"""TVL readers (Fu et al. 2024, Max-Fu/tvl): the HCT and SSVTP parts of the Touch-Vision-Language set.

Both parts share the TVL release and its split rule, so both plugins live here.

``tvl_hct`` reads ``<root>`` = ``tvl_dataset/hct``::

    <root>/data1/ data2/ data3/                 collection runs (option ``runs``)
      train.csv, test.csv                       header + 4 columns by position:
                                                vision, tactile, background, caption
      contact.json                              {"vision": [...], "tactile": [...], "background": [...]}
      <idx>-<unix_ts>/tactile/<frame>.jpg       DIGIT frames; vision/<frame>.jpg is its webcam pair

Paths in the CSVs and in contact.json are relative to their run folder; a listed pair must name
the same frame (same file name, same trajectory folder), or it is a bad sample.  The CSVs are the
default source (they carry the GPT-4V captions used as ``text``); ``source="contact_json"``
reads contact.json instead, without captions.

``tvl_ssvtp`` reads ``<root>`` = ``tvl_dataset/ssvtp``::

    <root>/train.csv, test.csv                  first column: images_rgb/image_<i>_rgb.jpg
    <root>/images_rgb/image_<i>_rgb.jpg         visual
    <root>/images_tac/image_<i>_tac.jpg         tactile, same index i
    <root>/text/labels_<i>.txt                  first line: comma-separated adjectives -> text

A first SSVTP CSV row whose first cell is not an ``image_<i>_rgb`` path is taken as a header.

Splits follow TVL's ``tacvis.py``: ``test`` is test.csv; ``train`` and ``val`` are the 90/10
``sklearn.model_selection.train_test_split(random_state=42)`` of train.csv (of all runs
concatenated in ``runs`` order, for HCT), in TVL's shuffled order; ``trainval`` is all of
train.csv in file order.  The split is taken over the rows as listed, before bad rows are
skipped, so it stays TVL's split either way.

Known HCT problem: the tactile/ and vision/ folders are swapped in parts of the original release
(Max-Fu/tvl issue #9; a fixed release is ``yoorhim/TVL-revise``).  Nothing is "fixed" silently:
``check_swap=true`` flags every pair whose tactile image has more pixels than its vision image,
assuming [unverified] that the webcam frames are larger than DIGIT frames (DIGIT streams at most
640x480).  This heuristic cannot see a swap when both cameras recorded the same resolution.  The
original contact.json also lists frames that do not load (Max-Fu/tvl #8): strict builds name the
first one, ``lenient=true`` skips them with a count.

Split groups (what ``split_dataset`` holds out whole): for HCT the trajectory folder
``<run>/<idx>-<unix_ts>/``, one recorded contact sequence whose frames are near-duplicates.
SSVTP names nothing but the sample index, so its samples are each their own group.
"""

from __future__ import annotations

import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import numpy as np

from vqtouch.core import BuildContext, DatasetError
from vqtouch.plugins.data.readers._io import (
    with_context_size,
    FileIndex,
    RecordDataset,
    SampleRecord,
    SkipLog,
    collect_records,
    loader_for,
    read_csv_rows,
    read_image_size,
    read_json,
    read_list_lines,
    require_file,
    require_folder,
    require_root,
)

from .tvl_plugin import HCT, SSVTP, TvlHctConfig, TvlSsvtpConfig

HCT_LAYOUT = "<root>/<run>/{train,test}.csv or contact.json, paths relative to each run folder (root = tvl_dataset/hct)"
SSVTP_LAYOUT = (
    "<root>/{train,test}.csv, <root>/images_rgb/image_<i>_rgb.jpg, <root>/images_tac/image_<i>_tac.jpg, "
    "<root>/text/labels_<i>.txt (root = tvl_dataset/ssvtp)"
)
# TVL's split: 90 % of train.csv for training, the rest for validation, seed 42.
TRAIN_FRACTION = 0.9
SPLIT_SEED = 42
HCT_COLUMNS = ("vision", "tactile", "background", "caption")
CONTACT_KEYS = ("vision", "tactile", "background")
SENSOR = "digit"
_SSVTP_IMAGE = re.compile(r"image_(?P<index>\d+)_rgb(?P<suffix>\.\w+)")

Row = TypeVar("Row")


def tvl_split(rows: Sequence[Row], split: str, source: str) -> list[Row]:
    """The rows of ``split`` chosen exactly as TVL chooses them (see the module docstring)."""
    if split in ("test", "trainval") or not rows:
        return list(rows)
    from sklearn.model_selection import train_test_split

    try:
        train_indices, val_indices = train_test_split(
            np.arange(len(rows)), train_size=TRAIN_FRACTION, random_state=SPLIT_SEED
        )
    except ValueError as exc:
        raise DatasetError(f"cannot make TVL's 90/10 train/val split of {source} ({len(rows)} rows): {exc}") from None
    return [rows[index] for index in (train_indices if split == "train" else val_indices)]


# --------------------------------------------------------------------------------------------
# HCT
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class HctRow:
    """One listed HCT pair before its files are checked."""

    run: str
    where: str
    cells: tuple[str, ...]


class TvlHctDataset(RecordDataset):
    """TVL HCT samples: DIGIT tactile frame, webcam frame, caption; split groups are trajectories."""


def _hct_rows_from_csv(root: Path, run: str, split: str) -> list[HctRow]:
    csv_path = require_file(root / run / ("test.csv" if split == "test" else "train.csv"), HCT, "split CSV")
    rows = read_csv_rows(csv_path, HCT)[1:]  # the first row is the header
    return [HctRow(run, f"{csv_path} line {number}", tuple(cells)) for number, cells in rows]


def _hct_rows_from_contact_json(root: Path, run: str) -> list[HctRow]:
    json_path = require_file(root / run / "contact.json", HCT, "pair list contact.json")
    lists = read_json(json_path, HCT)
    if not isinstance(lists, dict) or any(not isinstance(lists.get(key), list) for key in CONTACT_KEYS):
        raise DatasetError(f"{HCT}: {json_path} must be an object with lists {', '.join(CONTACT_KEYS)}")
    lengths = {key: len(lists[key]) for key in CONTACT_KEYS}
    if len(set(lengths.values())) != 1:
        # Parallel lists of different length: any pairing of them would be a guess.
        raise DatasetError(
            f"{HCT}: {json_path}: the parallel lists have different lengths "
            f"({', '.join(f'{key} {n}' for key, n in lengths.items())}); cannot pair them"
        )
    return [
        HctRow(run, f"{json_path} entry {index}", (*(str(lists[key][index]) for key in CONTACT_KEYS), ""))
        for index in range(lengths["vision"])
    ]


def same_frame(vision: str, tactile: str) -> bool:
    """Whether two HCT paths name the same frame: <trajectory>/vision/<name> and <trajectory>/tactile/<name>."""
    vision_path, tactile_path = Path(vision), Path(tactile)
    return vision_path.name == tactile_path.name and vision_path.parent.parent == tactile_path.parent.parent


def _swap_problem(tactile: Path, vision: Path) -> str | None:
    try:
        tactile_size, vision_size = read_image_size(tactile), read_image_size(vision)
    except DatasetError as exc:
        return str(exc)
    if tactile_size[0] * tactile_size[1] <= vision_size[0] * vision_size[1]:
        return None
    return (
        f"tactile image {tactile} ({tactile_size[0]}x{tactile_size[1]}) is larger than its vision image "
        f"{vision} ({vision_size[0]}x{vision_size[1]}): the tactile/ and vision/ folders look swapped "
        f"(Max-Fu/tvl #9); use the fixed release (yoorhim/TVL-revise), or lenient=true to skip such pairs"
    )


def _hct_candidates(rows: list[HctRow], root: Path, config: TvlHctConfig, skips: SkipLog) -> Iterator[SampleRecord]:
    files = FileIndex()
    for row in rows:
        if len(row.cells) != len(HCT_COLUMNS):
            skips.reject(
                f"{row.where}: expected {len(HCT_COLUMNS)} columns ({', '.join(HCT_COLUMNS)}), got {len(row.cells)}"
            )
            continue
        vision, tactile, background = (f"{row.run}/{cell}" for cell in row.cells[:3])
        caption = row.cells[3]
        wanted = [("vision", vision), ("tactile", tactile)]
        if config.subtract_background:
            wanted.append(("background", background))
        missing = [f"{kind} image {root / path}" for kind, path in wanted if not files.exists(root / path)]
        if missing:
            skips.reject(f"{row.where}: missing {' and '.join(missing)}")
            continue
        if not same_frame(vision, tactile):
            skips.reject(
                f"{row.where}: vision {vision} and tactile {tactile} are not the same frame (HCT pairs "
                f"share the file name and trajectory folder)"
            )
            continue
        if config.check_swap and (problem := _swap_problem(root / tactile, root / vision)):
            skips.reject(f"{row.where}: {problem}")
            continue
        yield SampleRecord(
            id=tactile,
            tactile=tactile,
            visual=vision,
            reference=background,
            text=caption,
            group=Path(tactile).parent.parent.as_posix(),
        )


def build_tvl_hct(config: TvlHctConfig, context: BuildContext) -> TvlHctDataset:
    """Factory: read the runs' CSVs (or contact.json), take TVL's split and check every pair."""
    config = with_context_size(config, context)
    root = require_root(config, HCT_LAYOUT)
    if config.source == "contact_json" and config.split == "test":
        raise DatasetError(
            f"{HCT}: contact.json has no test split (test pairs are listed only in test.csv); "
            f"use source='csv' or another split"
        )
    rows: list[HctRow] = []
    for run in config.runs:
        require_folder(root / run, HCT, f"collection run {run!r}")
        rows += (
            _hct_rows_from_csv(root, run, config.split)
            if config.source == "csv"
            else _hct_rows_from_contact_json(root, run)
        )
    listed_in = f"{config.split} rows of {', '.join(config.runs)} ({config.source}) under {root}"
    chosen = tvl_split(rows, config.split, listed_in)
    skips = SkipLog(HCT, config.lenient)
    loader = loader_for(config)
    records = collect_records(
        _hct_candidates(chosen, root, config, skips),
        config=config,
        skips=skips,
        base=root,
        loader=loader,
        use_reference=config.subtract_background,
        listed_in=listed_in,
        total=len(chosen),
    )
    return TvlHctDataset(
        records,
        base=root,
        loader=loader,
        sensor=SENSOR,
        subtract_reference=config.subtract_background,
        split_unit="trajectory",
    )


# --------------------------------------------------------------------------------------------
# SSVTP
# --------------------------------------------------------------------------------------------
class TvlSsvtpDataset(RecordDataset):
    """TVL SSVTP samples: tactile and visual image of index i, adjectives as text.  No split groups:
    the release records nothing that ties two indices to one recording or object."""


def _ssvtp_rows(csv_path: Path) -> list[tuple[int, list[str]]]:
    rows = read_csv_rows(csv_path, SSVTP)
    if rows and not _SSVTP_IMAGE.fullmatch(Path(rows[0][1][0]).name):
        rows = rows[1:]  # a header row
    return rows


def adjectives_text(first_line: str) -> str:
    """SSVTP's comma-separated adjectives, lower-cased and without periods, joined by ', '."""
    words = (word.strip() for word in first_line.replace(".", "").lower().split(","))
    return ", ".join(word for word in words if word)


def _ssvtp_candidates(
    rows: list[tuple[int, list[str]]], csv_path: Path, root: Path, skips: SkipLog
) -> Iterator[SampleRecord]:
    files = FileIndex()
    for number, cells in rows:
        where = f"{csv_path} line {number}"
        match = _SSVTP_IMAGE.fullmatch(Path(cells[0]).name)
        if match is None:
            skips.reject(f"{where}: first column must name images_rgb/image_<i>_rgb.<ext>, got {cells[0]!r}")
            continue
        index = match["index"]
        visual, tactile = cells[0], f"images_tac/image_{index}_tac{match['suffix']}"
        text_path = root / "text" / f"labels_{index}.txt"
        missing = [
            f"{kind} {root / path}"
            for kind, path in (("visual image", visual), ("tactile image", tactile))
            if not files.exists(root / path)
        ]
        if not files.exists(text_path):
            missing.append(f"adjective file {text_path}")
        if missing:
            skips.reject(f"{where}: missing {' and '.join(missing)}")
            continue
        try:
            lines = read_list_lines(text_path, SSVTP)
        except DatasetError as exc:
            skips.reject(f"{where}: {exc}")
            continue
        yield SampleRecord(
            id=tactile, tactile=tactile, visual=visual, text=adjectives_text(lines[0][1]) if lines else ""
        )


def build_tvl_ssvtp(config: TvlSsvtpConfig, context: BuildContext) -> TvlSsvtpDataset:
    """Factory: read the split CSV, pair images by index i and read the adjectives."""
    config = with_context_size(config, context)
    root = require_root(config, SSVTP_LAYOUT)
    csv_path = require_file(root / ("test.csv" if config.split == "test" else "train.csv"), SSVTP, "split CSV")
    chosen = tvl_split(_ssvtp_rows(csv_path), config.split, str(csv_path))
    skips = SkipLog(SSVTP, config.lenient)
    loader = loader_for(config)
    records = collect_records(
        _ssvtp_candidates(chosen, csv_path, root, skips),
        config=config,
        skips=skips,
        base=root,
        loader=loader,
        use_reference=False,
        listed_in=f"{config.split} rows of {csv_path}",
        total=len(chosen),
    )
    return TvlSsvtpDataset(records, base=root, loader=loader, sensor=SENSOR)

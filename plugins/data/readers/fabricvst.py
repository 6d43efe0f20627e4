"""FabricVST reader (Cao et al., RAS 2024): tactile images of 50 fabrics, labelled by fabric.

What is documented about the release (``RAS_dataset.zip``): ``visual/`` (one image per
fabric), ``visual_cropped/<Material_k>/`` (225 crops per fabric), ``tactile/`` (225 images per
fabric, sub-structure undocumented) and five annotator CSVs of 24 binary attributes (column
layout undocumented).  Whether crops and tactile images align by index is undocumented too, so
samples are tactile-only: pairing crops with tactile images would be a guess.

Assumptions [unverified], and the only layouts accepted (anything else fails, saying why):

1. ``tactile/<fabric>/<image>``: one sub-folder per fabric; fabrics = the sub-folder names.
2. ``tactile/<fabric>_<rest>.<ext>`` (or ``<fabric>-<rest>``): a flat folder whose file names
   start with a fabric name followed by ``_`` or ``-``; fabrics = the folder names of
   ``visual_cropped/``, and the longest matching name wins (``Material_10_3.png`` belongs to
   ``Material_10``, not ``Material_1``).  A file that matches no fabric is a bad sample.

``tactile/`` holding both images and folders is refused.  Labels index the fabrics in sorted
name order (plain string order).  Attributes are read only when ``attribute_csvs`` names the
annotator files and each has the simple layout ``fabric,<attribute>,...`` (header row, one row
per fabric, values 0/1, the same attribute columns in every file); they are aggregated by
majority (ties negative) and the positive ones become ``text`` ("soft, thin, ...").  The
tactile sensor model is undocumented: the ``sensor`` option names it.

Split groups: the fabric, the finest unit either layout names (the 225 images of one fabric are
touches of one piece of cloth), so ``split_dataset`` holds out whole fabrics, as the paper's
40/5/5 fabric split does; held-out fabrics are then classes the training never saw.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path

from vqtouch.core import BuildContext, DatasetError
from vqtouch.plugins.data.readers._io import (
    with_context_size,
    RecordDataset,
    SampleRecord,
    SkipLog,
    collect_records,
    list_images,
    loader_for,
    read_csv_rows,
    relative_posix,
    require_folder,
    require_root,
    resolve_under,
    visible_subfolders,
)

from .fabricvst_plugin import READER, FabricVstConfig

LAYOUT = "<root>/tactile/<fabric>/<image> or <root>/tactile/<fabric>_<n>.<ext> with <root>/visual_cropped/<fabric>/"
NAME_SEPARATORS = ("_", "-")
BINARY_VALUES = {"0": False, "1": True}


class FabricVstDataset(RecordDataset):
    """FabricVST samples: one tactile image each, labelled by fabric, attributes as text; split groups
    are fabrics."""

    def __init__(self, *args, attributes: dict[str, list[str]] | None = None, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        #: Majority-voted positive attributes of each fabric (empty without attribute CSVs).
        self.attributes = attributes or {}


def _fabric_of(file_name: str, fabrics_longest_first: Sequence[str]) -> str | None:
    for fabric in fabrics_longest_first:
        if any(file_name.startswith(fabric + separator) for separator in NAME_SEPARATORS):
            return fabric
    return None


def _tactile_files(root: Path, skips: SkipLog) -> dict[str, list[Path]]:
    """Tactile images grouped by fabric, from whichever accepted layout ``tactile/`` has."""
    tactile = require_folder(root / "tactile", READER, "tactile image")
    folders = visible_subfolders(tactile)
    files = list_images(tactile)
    if folders and files:
        raise DatasetError(
            f"{READER}: {tactile} holds both images and folders; expected either one sub-folder per "
            f"fabric or a flat folder of <fabric>_<n> images (see the reader's documentation)"
        )
    if folders:
        return {folder.name: list_images(folder) for folder in folders}
    visual_cropped = root / "visual_cropped"
    if not visual_cropped.is_dir():
        raise DatasetError(
            f"{READER}: {tactile} is flat, so fabric names come from the folders of {visual_cropped}, which is missing"
        )
    names = [folder.name for folder in visible_subfolders(visual_cropped)]
    grouped: dict[str, list[Path]] = {name: [] for name in names}
    longest_first = sorted(names, key=len, reverse=True)
    for image in files:
        fabric = _fabric_of(image.name, longest_first)
        if fabric is None:
            skips.reject(
                f"tactile image {image} does not start with a fabric name of {visual_cropped} followed by '_' or '-'"
            )
            continue
        grouped[fabric].append(image)
    return grouped


def _read_votes(path: Path) -> tuple[list[str], dict[str, list[bool]]]:
    rows = read_csv_rows(path, READER)
    if not rows or len(rows[0][1]) < 2:
        raise DatasetError(f"{READER}: {path}: expected a header 'fabric,<attribute>,...'")
    attributes = rows[0][1][1:]
    votes: dict[str, list[bool]] = {}
    for number, cells in rows[1:]:
        fabric, values = cells[0], cells[1:]
        if len(values) != len(attributes) or any(value not in BINARY_VALUES for value in values):
            raise DatasetError(
                f"{READER}: {path} line {number}: expected a fabric name and {len(attributes)} values 0/1, got {cells}"
            )
        if fabric in votes:
            raise DatasetError(f"{READER}: {path} line {number}: fabric {fabric!r} is listed twice")
        votes[fabric] = [BINARY_VALUES[value] for value in values]
    return attributes, votes


def read_attributes(paths: Sequence[Path], fabrics: Sequence[str]) -> dict[str, list[str]]:
    """Positive attributes of each fabric by majority over the annotator CSVs (ties are negative)."""
    tables = [(path, *_read_votes(path)) for path in paths]
    attributes = tables[0][1]
    for path, other, votes in tables:
        if other != attributes:
            raise DatasetError(f"{READER}: {path} has attribute columns {other}; {tables[0][0]} has {attributes}")
        missing = [fabric for fabric in fabrics if fabric not in votes]
        if missing:
            raise DatasetError(f"{READER}: {path} has no row for fabric(s) {missing[:5]}")
    return {
        fabric: [
            attribute
            for column, attribute in enumerate(attributes)
            if 2 * sum(votes[fabric][column] for _, _, votes in tables) > len(tables)
        ]
        for fabric in fabrics
    }


def _candidates(
    grouped: dict[str, list[Path]],
    chosen: Sequence[str],
    label_of: dict[str, int],
    root: Path,
    attributes: dict[str, list[str]],
) -> Iterator[SampleRecord]:
    for fabric in chosen:
        text = ", ".join(attributes.get(fabric, []))
        for image in grouped[fabric]:
            path = relative_posix(image, root)
            yield SampleRecord(id=path, tactile=path, label=label_of[fabric], text=text, group=fabric)


def build_fabricvst(config: FabricVstConfig, context: BuildContext) -> FabricVstDataset:
    """Factory: group the tactile images by fabric, label them and attach attributes if asked."""
    config = with_context_size(config, context)
    root = require_root(config, LAYOUT)
    skips = SkipLog(READER, config.lenient)
    grouped = _tactile_files(root, skips)
    fabrics = sorted(grouped)
    unknown = [fabric for fabric in config.fabrics if fabric not in grouped]
    if unknown:
        raise DatasetError(f"{READER}: unknown fabric(s) {unknown}; the dataset has: {', '.join(fabrics)}")
    chosen = list(config.fabrics) or fabrics
    attributes = (
        read_attributes([resolve_under(path, root) for path in config.attribute_csvs], fabrics)
        if config.attribute_csvs
        else {}
    )
    loader = loader_for(config)
    candidates = _candidates(grouped, chosen, {fabric: label for label, fabric in enumerate(fabrics)}, root, attributes)
    records = collect_records(
        candidates,
        config=config,
        skips=skips,
        base=root,
        loader=loader,
        use_reference=False,
        listed_in=f"{root / 'tactile'} (fabrics {', '.join(chosen)})",
        total=sum(len(grouped[fabric]) for fabric in chosen),
    )
    return FabricVstDataset(
        records,
        base=root,
        loader=loader,
        sensor=config.sensor,
        class_names=fabrics,
        attributes=attributes,
        split_unit="fabric",
    )

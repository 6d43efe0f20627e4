"""The ``objectfolder_real`` and ``objectfolder_cross`` readers' plugin: their options and registration (the
readers, in objectfolder.py, are imported when built)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from vqtouch.core import hookimpl

from ._options import ReaderConfig

REAL = "objectfolder_real"
CROSS = "objectfolder_cross"


class ObjectFolderRealConfig(ReaderConfig):
    """Options of the ``objectfolder_real`` reader (GelSight recordings of 100 real objects)."""

    name: Literal["objectfolder_real"] = "objectfolder_real"
    root: str = Field(
        "",
        description="ObjectFolder-Real folder with one folder per object index: "
        "<root>/<obj_idx>/tactile_data/<trial_idx>/0/gelsight/*.png. Required.",
    )
    metadata_csv: str = Field(
        "",
        description="T3's objectfolder_real_metadata.csv (columns Index, Name, Material) "
        "giving each object's material label; empty uses "
        "<root>/objectfolder_real_metadata.csv when present, else labels are -1.",
    )
    objects: tuple[int, ...] = Field(
        (),
        max_length=100_000,
        description="Object indices to read (e.g. an object-level split); empty reads every object folder.",
    )


class ObjectFolderCrossConfig(ReaderConfig):
    """Options of the ``objectfolder_cross`` reader (ObjectFolder visuo-tactile cross-generation benchmark)."""

    name: Literal["objectfolder_cross"] = "objectfolder_cross"
    root: str = Field(
        "",
        description="Benchmark data folder holding vision/<obj>/<contact>.png, "
        "touch/<obj>/<contact>.png and touch_ref/touch_ref.png. Required.",
    )
    split_file: str = Field(
        "split.json",
        min_length=1,
        description="Split JSON {'train': [[obj, contact], ...], 'val': ..., 'test': ...} "
        "(cross-contact or cross-object); relative to root unless absolute.",
    )
    split: Literal["train", "val", "test"] = Field("train", description="Which list of the split JSON to read.")
    subtract_reference: bool = Field(
        False,
        description="Return tactile - touch_ref/touch_ref.png + 0.5, clamped to "
        "[0, 1] (shows only what contact changed).",
    )


@hookimpl
def vqtouch_register_datasets(register):
    register(
        REAL,
        "vqtouch.plugins.data.readers.objectfolder:build_objectfolder_real",
        ObjectFolderRealConfig,
        description="ObjectFolder-Real: GelSight frames of 100 real objects, labelled by material (T3 metadata).",
    )
    register(
        CROSS,
        "vqtouch.plugins.data.readers.objectfolder:build_objectfolder_cross",
        ObjectFolderCrossConfig,
        description="ObjectFolder cross-generation benchmark: paired touch and vision patches, labelled by object.",
    )

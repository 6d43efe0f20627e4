"""The ``visgel`` reader's plugin: its options and registration (the reader, in visgel.py, is imported
when built)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from vqtouch.core import hookimpl

from ._options import ReaderConfig

READER = "visgel"


class VisGelConfig(ReaderConfig):
    """Options of the ``visgel`` reader (GelSight + camera frames from the VisGel lists)."""

    name: Literal["visgel"] = "visgel"
    root: str = Field(
        "",
        description="VisGel folder holding data_lst/ and the data folders its lists name "
        "(paths in the lists are relative to it). Required.",
    )
    split: Literal["train", "eval", "demo"] = Field(
        "train", description="List to read: data_lst/<split>_<direction>.txt."
    )
    direction: Literal["vision2touch", "touch2vision"] = Field(
        "vision2touch",
        description="Which list family to read; both give visual and tactile images, the "
        "direction only decides which list (and which reference column) is used.",
    )
    subtract_reference: bool = Field(
        False,
        description="Return tactile - no-contact reference frame + 0.5, clamped "
        "to [0, 1] (shows only what contact changed).",
    )


@hookimpl
def vqtouch_register_datasets(register):
    register(
        READER,
        "vqtouch.plugins.data.readers.visgel:build_visgel",
        VisGelConfig,
        description="VisGel: GelSight frames paired with camera frames from the data_lst lists (no labels).",
    )

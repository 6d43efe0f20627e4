"""The ``fabricvst`` reader's plugin: its options and registration (the reader, in fabricvst.py, is imported
when built)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from vqtouch.core import hookimpl

from ._options import ReaderConfig

READER = "fabricvst"


class FabricVstConfig(ReaderConfig):
    """Options of the ``fabricvst`` reader (tactile images of 50 fabrics; layout partly assumed)."""

    name: Literal["fabricvst"] = "fabricvst"
    root: str = Field(
        "",
        description="Unzipped FabricVST folder holding tactile/ (as tactile/<fabric>/<image>, or "
        "flat tactile/<fabric>_<n>.<ext> next to visual_cropped/<fabric>/). Required.",
    )
    fabrics: tuple[str, ...] = Field(
        (),
        max_length=10_000,
        description="Fabric names to read (e.g. the paper's 40/5/5 fabric split); empty "
        "reads all. Labels always index all fabrics.",
    )
    attribute_csvs: tuple[str, ...] = Field(
        (),
        max_length=64,
        description="Annotator CSVs (relative to root unless absolute) with header "
        "'fabric,<attribute>,...' and 0/1 values; majority-voted positive attributes "
        "become the text. Empty: no attributes (the release's CSV layout is "
        "undocumented).",
    )
    sensor: str = Field(
        "fabricvst",
        min_length=1,
        max_length=64,
        description="Sensor id reported with every sample (FabricVST's sensor model is undocumented).",
    )


@hookimpl
def vqtouch_register_datasets(register):
    register(
        READER,
        "vqtouch.plugins.data.readers.fabricvst:build_fabricvst",
        FabricVstConfig,
        description="FabricVST: tactile images of 50 fabrics labelled by fabric, optional majority-voted "
        "attributes as text (layout partly assumed, see the module docs).",
    )

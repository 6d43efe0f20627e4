"""The ``touch_and_go`` reader's plugin: its options and registration (the reader, in touch_and_go.py, is
imported when built)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from vqtouch.core import hookimpl

from ._options import ReaderConfig

READER = "touch_and_go"
ROUGH_SPLITS = frozenset({"train_rough", "test_rough"})


class TouchAndGoConfig(ReaderConfig):
    """Options of the ``touch_and_go`` reader (GelSight + video frames, material labels)."""

    name: Literal["touch_and_go"] = "touch_and_go"
    root: str = Field(
        "",
        description="Touch and Go folder holding dataset/<recording>/{video_frame,gelsight_frame}/, "
        "dataset/<split>.txt, label.txt and category_reference.txt. Required.",
    )
    split: Literal["train", "test", "pretrain", "train_rough", "test_rough", "all"] = Field(
        "train",
        description="List to read: dataset/<split>.txt, or 'all' for label.txt. The *_rough lists carry "
        "binary rough/smooth labels (which of 0/1 is rough is undocumented).",
    )
    labels: Literal["material", "hard_soft"] = Field(
        "material",
        description="Labels of the material lists: the categories of category_reference.txt, or "
        "hard/soft (ids 7, 8, 9, 11, 13 are soft, as in the repository's dataset.py).",
    )

    @model_validator(mode="after")
    def _hard_soft_needs_material_labels(self) -> TouchAndGoConfig:
        if self.labels == "hard_soft" and self.split in ROUGH_SPLITS:
            raise ValueError(
                f"labels='hard_soft' is derived from material ids; split {self.split!r} has "
                f"rough/smooth labels: use labels='material' or a material split"
            )
        return self


@hookimpl
def vqtouch_register_datasets(register):
    register(
        READER,
        "vqtouch.plugins.data.readers.touch_and_go:build_touch_and_go",
        TouchAndGoConfig,
        description="Touch and Go: GelSight frames paired with video frames, 20 material classes "
        "(or hard/soft, rough/smooth).",
    )

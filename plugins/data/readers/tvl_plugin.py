"""The TVL readers' plugin (``tvl_hct`` and ``tvl_ssvtp``): their options and registration (the readers, in
tvl.py, are imported when built)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from vqtouch.core import hookimpl

from ._options import ReaderConfig

HCT = "tvl_hct"
SSVTP = "tvl_ssvtp"
Split = Literal["train", "val", "test", "trainval"]
SPLIT_DESCRIPTION = (
    "'test' = test.csv; 'train'/'val' = TVL's 90/10 split of train.csv "
    "(sklearn train_test_split, random_state=42); 'trainval' = all of train.csv."
)


class TvlHctConfig(ReaderConfig):
    """Options of the ``tvl_hct`` reader (DIGIT + webcam frames with GPT-4V captions)."""

    name: Literal["tvl_hct"] = "tvl_hct"
    root: str = Field(
        "", description="The HCT folder of the TVL release (tvl_dataset/hct), holding the run folders. Required."
    )
    runs: tuple[str, ...] = Field(
        ("data1", "data2", "data3"),
        min_length=1,
        max_length=64,
        description="Collection-run folders under root to read, in this order (the "
        "train/val split is taken over their rows concatenated).",
    )
    split: Split = Field("train", description=f"Which samples: {SPLIT_DESCRIPTION}")
    source: Literal["csv", "contact_json"] = Field(
        "csv",
        description="Where pairs are listed: 'csv' reads train.csv/test.csv (with captions as text); "
        "'contact_json' reads contact.json (all contact frames, no captions, no test split).",
    )
    subtract_background: bool = Field(
        False,
        description="Return tactile - the trajectory's background frame + 0.5, "
        "clamped to [0, 1] (TVL's background subtraction).",
    )
    check_swap: bool = Field(
        False,
        description="Flag pairs whose tactile image is larger than the vision image, the "
        "sign of HCT's swapped tactile/vision folders (error, or skip when "
        "lenient; a heuristic based on image size, never a silent fix).",
    )


class TvlSsvtpConfig(ReaderConfig):
    """Options of the ``tvl_ssvtp`` reader (robot-collected DIGIT + camera pairs with adjectives)."""

    name: Literal["tvl_ssvtp"] = "tvl_ssvtp"
    root: str = Field(
        "",
        description="The SSVTP folder of the TVL release (tvl_dataset/ssvtp) holding train.csv, "
        "test.csv, images_rgb/, images_tac/ and text/. Required.",
    )
    split: Split = Field("train", description=f"Which samples: {SPLIT_DESCRIPTION}")


@hookimpl
def vqtouch_register_datasets(register):
    register(
        HCT,
        "vqtouch.plugins.data.readers.tvl:build_tvl_hct",
        TvlHctConfig,
        description="TVL HCT: DIGIT frames paired with webcam frames and GPT-4V captions (TVL's splits).",
    )
    register(
        SSVTP,
        "vqtouch.plugins.data.readers.tvl:build_tvl_ssvtp",
        TvlSsvtpConfig,
        description="TVL SSVTP: DIGIT images paired with camera images and human adjectives (TVL's splits).",
    )

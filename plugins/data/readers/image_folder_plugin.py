"""The ``image_folder`` reader's plugin: its options and registration (the reader, in image_folder.py, is imported
when built)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from vqtouch.core import hookimpl

from ._options import ReaderConfig

READER = "image_folder"


class ImageFolderConfig(ReaderConfig):
    """Options of the ``image_folder`` reader (class folders or a path,label[,visual] CSV)."""

    name: Literal["image_folder"] = "image_folder"
    root: str = Field(
        "",
        description="Folder with one sub-folder of images per class, or the folder that the csv "
        "path is relative to. Required.",
    )
    csv: str = Field(
        "",
        description="CSV with columns path,label and optionally visual,text,group (relative to "
        "root unless absolute; paths inside are relative to the CSV's folder; rows with "
        "the same group, e.g. frames of one recording, stay on one side of a "
        "train/held-out split; other columns are ignored). Empty: read class "
        "sub-folders of root, grouped by the sub-folder below each class folder.",
    )
    class_names: tuple[str, ...] = Field(
        (),
        max_length=1_000_000,
        description="Fixed class order: folder and label names must be in it and integer "
        "labels below its length. Empty: derived from the folders or labels.",
    )
    sensor: str = Field("unknown", min_length=1, max_length=64, description="Sensor id reported with every sample.")
    paths_outside: bool = Field(
        False,
        description="Let the CSV's rows name images outside its folder (``../``, "
        "absolute paths), e.g. a shared image store. Off: such a row is "
        "refused, naming its line.",
    )


@hookimpl
def vqtouch_register_datasets(register):
    register(
        READER,
        "vqtouch.plugins.data.readers.image_folder:build_image_folder",
        ImageFolderConfig,
        description="Generic tactile images: one sub-folder per class, or a path,label[,visual] CSV.",
    )

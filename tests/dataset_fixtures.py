"""Tiny on-disk copies of each dataset layout, for ``tests/test_datasets_readers.py``.

Every image is one flat colour so that a test can read back which file it came from: the red
channel encodes a sample number (``STEP`` apart, robust to JPEG rounding) and green/blue say
whether the file is a tactile or a visual image.  Sizes alternate between 32x24 and 30x40 so
both crop orientations are exercised.  Everything is deterministic.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

STEP = 10  # sample numbers stay <= 25 so that number * STEP fits in 8 bits
TACTILE_GREEN_BLUE = (220, 40)
VISUAL_GREEN_BLUE = (40, 220)
REFERENCE_COLOUR = (60, 100, 140)
TACTILE_SIZE = (24, 32)  # (width, height): DIGIT-like, smaller than the visual frames
VISUAL_SIZE = (40, 30)


# --------------------------------------------------------------------------------------------
# Images
# --------------------------------------------------------------------------------------------
def colour(number: int, modality: str) -> tuple[int, int, int]:
    """The flat colour of sample ``number``'s ``modality`` ("tactile" or "visual") image."""
    green, blue = TACTILE_GREEN_BLUE if modality == "tactile" else VISUAL_GREEN_BLUE
    return (number * STEP, green, blue)


def write_image(
    path: Path, rgb: tuple[int, int, int], size: tuple[int, int] = TACTILE_SIZE, mode: str = "RGB", alpha: int = 255
) -> Path:
    """Write a flat-colour image (format from the suffix) in ``mode``: RGB, L or RGBA."""
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    image = Image.new("RGB", size, rgb)
    if mode == "L":
        image = image.convert("L")
    elif mode == "RGBA":
        image = image.convert("RGBA")
        image.putalpha(alpha)
    image.save(path, quality=95) if path.suffix.lower() in {".jpg", ".jpeg"} else image.save(path)
    return path


def write_sample(path: Path, number: int, modality: str) -> Path:
    """Write sample ``number``'s image of ``modality`` at the modality's size."""
    return write_image(path, colour(number, modality), TACTILE_SIZE if modality == "tactile" else VISUAL_SIZE)


def write_frames(path: Path, image_format: str, count: int = 2) -> Path:
    """Write ``count`` flat-colour frames into one file: an animated GIF or PNG, or a multi-page TIFF.

    ``image_format`` (a Pillow format name) is used whatever the suffix: readers identify
    images by their content, so a ``.jpg`` frame may hold an animation.
    """
    from PIL import Image

    frames = [Image.new("RGB", TACTILE_SIZE, (number * STEP, 0, 0)) for number in range(count)]
    frames[0].save(path, format=image_format, save_all=True, append_images=frames[1:])
    return path


def write_16_bit(path: Path) -> Path:
    """Write a 16-bit greyscale PNG (mode I;16, which readers refuse) whatever the suffix."""
    from PIL import Image

    Image.new("I;16", TACTILE_SIZE, 1000).save(path, format="PNG")
    return path


def break_link(path: Path) -> Path:
    """Replace the file at ``path`` by a symbolic link to a file that does not exist; returns the target."""
    target = path.with_name(f"{path.name}.gone")
    path.unlink()
    path.symlink_to(target)
    return target


def truncate_pixels(path: Path) -> Path:
    """Cut a PNG or JPEG file inside its pixel data, as an interrupted download may: the header
    still reads, so only decoding finds the damage."""
    data = path.read_bytes()
    pixels = data.index(b"IDAT" if data.startswith(b"\x89PNG") else b"\xff\xda") + 4
    path.write_bytes(data[: (pixels + len(data)) // 2])
    return path


def write_text(path: Path, text: str) -> Path:
    """Write a UTF-8 text file, creating its folder."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return path


def sample_number(image_3HW: torch.Tensor) -> int:
    """The sample number encoded in an image's red channel."""
    return round(float(image_3HW[0].mean()) * 255 / STEP)


def modality(image_3HW: torch.Tensor) -> str:
    """Which kind of file an image was decoded from: "tactile" or "visual"."""
    return "tactile" if float(image_3HW[1].mean()) > float(image_3HW[2].mean()) else "visual"


# --------------------------------------------------------------------------------------------
# Touch and Go
# --------------------------------------------------------------------------------------------
TAG_RECORDINGS = ("20220410_031604", "20220517_192217")
TAG_CLASSES = [
    "Concrete",
    "Plastic",
    "Glass",
    "Wood",
    "Metal",
    "Brick",
    "Tile",
    "Leather",
    "Synthetic Fabric",
    "Natural Fabric",
    "Rubber",
    "Paper",
    "Tree",
    "Grass",
    "Soil",
    "Rock",
    "Gravel",
    "Sand",
    "Plants",
    "Others (foam: soft)",
]
# (sample number, label) per list; -1 is "Inconclusive".
TAG_LISTS = {
    "train": [(0, 8), (1, 3), (2, -1), (3, 13)],
    "test": [(4, 0), (5, 19)],
    "train_rough": [(0, 1), (1, 0)],
    "test_rough": [(4, 0)],
}


def tag_key(number: int) -> str:
    """The list key ("<recording>/<frame>.jpg") of sample ``number``."""
    return f"{TAG_RECORDINGS[number % 2]}/{number:010d}.jpg"


def tag_line(number: int, label: int) -> str:
    return f"{tag_key(number)},{label}"


def build_touch_and_go(root: Path) -> Path:
    """Touch and Go: frames, split lists, label.txt and category_reference.txt."""
    for number in range(6):
        recording, frame = tag_key(number).split("/")
        write_sample(root / "dataset" / recording / "gelsight_frame" / frame, number, "tactile")
        write_sample(root / "dataset" / recording / "video_frame" / frame, number, "visual")
    for split, entries in TAG_LISTS.items():
        write_text(root / "dataset" / f"{split}.txt", "".join(tag_line(n, label) + "\n" for n, label in entries))
    material_lines = [tag_line(n, label) for n, label in TAG_LISTS["train"] + TAG_LISTS["test"]]
    write_text(root / "label.txt", "\n".join(material_lines) + "\n")
    categories = ["Inconclusive: -1"] + [f"{name}: {class_id}" for class_id, name in enumerate(TAG_CLASSES)]
    write_text(root / "category_reference.txt", "\n".join(categories) + "\n")
    return root


# --------------------------------------------------------------------------------------------
# VisGel
# --------------------------------------------------------------------------------------------
VISGEL_NUMBERS = (1, 2, 3)


def visgel_frame(number: int, modality_name: str) -> str:
    """Relative path of a VisGel frame; number 0 is the no-contact reference."""
    sensor = "gelsight" if modality_name == "tactile" else "camera"
    return f"data_seen/7/rec_a/{sensor}/frame{number:04d}.png"


def build_visgel(root: Path) -> Path:
    """VisGel: frames under data_seen/ and the train/eval lists of both directions."""
    write_image(root / visgel_frame(0, "tactile"), REFERENCE_COLOUR)
    write_image(root / visgel_frame(0, "visual"), REFERENCE_COLOUR, VISUAL_SIZE)
    for number in VISGEL_NUMBERS:
        write_sample(root / visgel_frame(number, "tactile"), number, "tactile")
        write_sample(root / visgel_frame(number, "visual"), number, "visual")
    for direction, (src, des) in {"vision2touch": ("visual", "tactile"), "touch2vision": ("tactile", "visual")}.items():
        lines = [
            " ".join(
                [
                    visgel_frame(0, src),
                    visgel_frame(0, des),
                    visgel_frame(n, src),
                    visgel_frame(n, des),
                    *[visgel_frame(n, src)] * 4,
                ]
            )
            for n in VISGEL_NUMBERS
        ]
        write_text(root / "data_lst" / f"train_{direction}.txt", "\n".join(lines) + "\n")
        write_text(root / "data_lst" / f"eval_{direction}.txt", lines[0] + "\n")
    return root


# --------------------------------------------------------------------------------------------
# TVL HCT and SSVTP
# --------------------------------------------------------------------------------------------
# Per run: sample numbers in train.csv and test.csv.
HCT_RUNS = {
    "data1": {"train": list(range(0, 6)), "test": [11, 12]},
    "data2": {"train": list(range(6, 11)), "test": [13]},
}


def hct_paths(number: int) -> tuple[str, str, str]:
    """(vision, tactile, background) of HCT sample ``number``, relative to its run folder."""
    trajectory = f"{number // 3}-{1700000000 + number // 3}"
    frame = f"{number}-{1700000000.5 + number}.jpg"
    return f"{trajectory}/vision/{frame}", f"{trajectory}/tactile/{frame}", f"{trajectory}/background.jpg"


def hct_caption(number: int) -> str:
    """The caption of HCT sample ``number`` (it holds a comma, so the CSV quotes it)."""
    return f"smooth, cool (sample {number})"


def build_tvl_hct(root: Path) -> Path:
    """TVL HCT: two runs, each with train.csv, test.csv and contact.json."""
    for run, splits in HCT_RUNS.items():
        numbers = splits["train"] + splits["test"]
        for number in numbers:
            vision, tactile, background = hct_paths(number)
            write_sample(root / run / vision, number, "visual")
            write_sample(root / run / tactile, number, "tactile")
            write_image(root / run / background, REFERENCE_COLOUR)
        for split in ("train", "test"):
            rows = ["vision,tactile,background,caption"]
            rows += [",".join(hct_paths(n)) + f',"{hct_caption(n)}"' for n in splits[split]]
            write_text(root / run / f"{split}.csv", "\n".join(rows) + "\n")
        columns = list(zip(*(hct_paths(n) for n in numbers)))
        write_text(
            root / run / "contact.json",
            json.dumps({"vision": list(columns[0]), "tactile": list(columns[1]), "background": list(columns[2])}),
        )
    return root


SSVTP_TRAIN = list(range(1, 13))
SSVTP_TEST = [20, 21]


def ssvtp_adjectives(number: int) -> str:
    """First line of labels_<i>.txt: capitalised, with a period, as in the release."""
    return f"Smooth, Hard, Grade{number}."


def build_tvl_ssvtp(root: Path) -> Path:
    """TVL SSVTP: train.csv (with a header), test.csv (without), images and adjective files."""
    for number in SSVTP_TRAIN + SSVTP_TEST:
        write_sample(root / "images_rgb" / f"image_{number}_rgb.jpg", number, "visual")
        write_sample(root / "images_tac" / f"image_{number}_tac.jpg", number, "tactile")
        write_text(root / "text" / f"labels_{number}.txt", ssvtp_adjectives(number) + "\nsecond line ignored\n")
    write_text(root / "train.csv", "url\n" + "".join(f"images_rgb/image_{n}_rgb.jpg\n" for n in SSVTP_TRAIN))
    write_text(root / "test.csv", "".join(f"images_rgb/image_{n}_rgb.jpg\n" for n in SSVTP_TEST))
    return root


# --------------------------------------------------------------------------------------------
# ObjectFolder
# --------------------------------------------------------------------------------------------
# object index -> {trial: frame count}; sample numbers run over objects, trials and frames in order.
OF_REAL_OBJECTS = {1: {0: 2, 1: 1}, 2: {0: 2}, 3: {2: 2}}
OF_REAL_MATERIALS = {1: "Ceramic", 2: "Steel", 3: "Ceramic"}


def of_real_frames() -> list[tuple[int, int, int, int]]:
    """(object, trial, frame, sample number) of every ObjectFolder-Real frame, in reading order."""
    frames = []
    for obj, trials in OF_REAL_OBJECTS.items():
        for trial, count in trials.items():
            frames += [(obj, trial, frame) for frame in range(count)]
    return [(*frame, number) for number, frame in enumerate(frames)]


def build_objectfolder_real(root: Path, metadata: bool = True) -> Path:
    """ObjectFolder-Real: object/trial folders of GelSight PNGs (plus ignored JPEG copies) and metadata."""
    for obj, trial, frame, number in of_real_frames():
        folder = root / str(obj) / "tactile_data" / str(trial) / "0" / "gelsight"
        write_sample(folder / f"{frame}.png", number, "tactile")
        write_sample(folder / f"{frame}.jpg", 9, "visual")  # T3's conversion leaves these behind
    write_text(root / "README" / "notes.txt", "not an object folder")
    if metadata:
        rows = ["Index,Name,Material"] + [f"{obj},object {obj},{OF_REAL_MATERIALS[obj]}" for obj in OF_REAL_OBJECTS]
        write_text(root / "objectfolder_real_metadata.csv", "\n".join(rows) + "\n")
    return root


OF_CROSS_SPLITS = {"train": [[1, 0], [1, 1], [2, 0], [3, 0]], "val": [[1, 2]], "test": [[2, 1], [10, 0]]}


def of_cross_number(obj: int, contact: int) -> int:
    return obj + contact


def build_objectfolder_cross(root: Path) -> Path:
    """ObjectFolder cross-generation: touch/ and vision/ patches, touch_ref and split.json."""
    for entries in OF_CROSS_SPLITS.values():
        for obj, contact in entries:
            write_sample(root / "touch" / str(obj) / f"{contact}.png", of_cross_number(obj, contact), "tactile")
            write_sample(root / "vision" / str(obj) / f"{contact}.png", of_cross_number(obj, contact), "visual")
    write_image(root / "touch_ref" / "touch_ref.png", REFERENCE_COLOUR)
    write_text(root / "split.json", json.dumps(OF_CROSS_SPLITS))
    return root


# --------------------------------------------------------------------------------------------
# FabricVST
# --------------------------------------------------------------------------------------------
FABRICS = {"Material_1": 2, "Material_10": 1, "Material_2": 1}  # fabric -> tactile images
FABRIC_ATTRIBUTES = ["soft", "rough", "shinny"]
# Three annotators' votes per fabric, in FABRIC_ATTRIBUTES order.
FABRIC_VOTES = {
    "Material_1": [(1, 0, 1), (1, 0, 0), (0, 1, 0)],
    "Material_10": [(0, 1, 1), (0, 1, 1), (0, 0, 1)],
    "Material_2": [(1, 1, 0), (0, 0, 0), (0, 1, 0)],
}


def build_fabricvst(root: Path, flat: bool = False) -> Path:
    """FabricVST: visual_cropped/<fabric>/ and tactile/ per fabric (or flat), plus annotator CSVs."""
    number = 0
    for fabric, count in FABRICS.items():
        write_sample(root / "visual_cropped" / fabric / "0.jpg", 0, "visual")
        for index in range(count):
            separator = "-" if fabric == "Material_2" else "_"  # both separators are accepted
            name = f"{fabric}{separator}{index}.png" if flat else f"{fabric}/{index}.png"
            write_sample(root / "tactile" / name, number, "tactile")
            number += 1
    for annotator in range(3):
        rows = ["fabric," + ",".join(FABRIC_ATTRIBUTES)]
        rows += [f"{fabric}," + ",".join(str(v) for v in votes[annotator]) for fabric, votes in FABRIC_VOTES.items()]
        write_text(root / f"annotator_{annotator}.csv", "\n".join(rows) + "\n")
    return root


def fabric_numbers() -> dict[str, list[int]]:
    """Sample numbers written for each fabric, in writing order."""
    numbers, start = {}, 0
    for fabric, count in FABRICS.items():
        numbers[fabric] = list(range(start, start + count))
        start += count
    return numbers


# --------------------------------------------------------------------------------------------
# Image folder
# --------------------------------------------------------------------------------------------
IMAGE_FOLDER_CLASSES = {"rough": [0, 1], "smooth": [2]}


def build_image_folder(root: Path) -> Path:
    """Class folders under root/classes (one image nested deeper) and images for a CSV under root/listed."""
    for class_name, numbers in IMAGE_FOLDER_CLASSES.items():
        for number in numbers:
            nested = "nested/" if number == 1 else ""
            write_sample(root / "classes" / class_name / f"{nested}img{number}.png", number, "tactile")
    for number in range(3, 7):
        write_sample(root / "listed" / "touch" / f"{number}.png", number, "tactile")
        write_sample(root / "listed" / "vision" / f"{number}.png", number, "visual")
    return root


def write_image_folder_csv(root: Path, labels: Sequence[str], visual: bool = True) -> Path:
    """A CSV over samples 3.. with the given label cells (paths relative to the CSV's folder)."""
    header = "path,label,visual" if visual else "label,path"
    rows = [header]
    for number, label in zip(range(3, 7), labels):
        rows.append(f"touch/{number}.png,{label},vision/{number}.png" if visual else f"{label},touch/{number}.png")
    return write_text(root / "listed" / "list.csv", "\n".join(rows) + "\n")


# --------------------------------------------------------------------------------------------
# One description per reader, for the tests that every reader must pass
# --------------------------------------------------------------------------------------------
@dataclass
class ReaderCase:
    """How to build a reader's fixture and where its list lives, for the shared bad-input tests.

    ``build(folder)`` writes the layout under ``folder`` and returns the dataset root; the
    other callables take that root.  ``length`` is the sample count with ``options``.
    """

    name: str
    module: str
    build: Callable[[Path], Path]
    options: dict[str, Any] = field(default_factory=dict)
    length: int = 0
    list_file: Callable[[Path], Path] | None = None
    empty_split: Callable[[Path], None] | None = None

    def config(self, root: Path, **extra: Any) -> dict[str, Any]:
        """The dataset config block for this reader on ``root``."""
        return {"name": self.name, "root": str(root), "image_size": 16, **self.options, **extra}


def _empty_list(relative: str, keep_header: bool = False) -> Callable[[Path], None]:
    def empty(root: Path) -> None:
        path = root / relative
        header = path.read_text().splitlines()[0] + "\n" if keep_header else ""
        path.write_text(header)

    return empty


def _empty_hct(root: Path) -> None:
    for run in HCT_RUNS:
        _empty_list(f"{run}/test.csv", keep_header=True)(root)


def _empty_objectfolder_real(root: Path) -> None:
    for obj in OF_REAL_OBJECTS:
        for image in (root / str(obj)).rglob("*.png"):
            image.unlink()


def _empty_fabricvst(root: Path) -> None:
    for image in (root / "tactile").rglob("*.png"):
        image.unlink()


def _empty_image_folder(root: Path) -> None:
    for image in root.rglob("*.png"):
        image.unlink()


def _empty_objectfolder_cross(root: Path) -> None:
    write_text(root / "split.json", json.dumps({**OF_CROSS_SPLITS, "train": []}))


READER_CASES = [
    ReaderCase(
        "touch_and_go",
        "vqtouch.plugins.data.readers.touch_and_go_plugin",
        build_touch_and_go,
        {"split": "train"},
        3,
        lambda root: root / "dataset" / "train.txt",
        _empty_list("dataset/train.txt"),
    ),
    ReaderCase(
        "visgel",
        "vqtouch.plugins.data.readers.visgel_plugin",
        build_visgel,
        {},
        3,
        lambda root: root / "data_lst" / "train_vision2touch.txt",
        _empty_list("data_lst/train_vision2touch.txt"),
    ),
    ReaderCase(
        "tvl_hct",
        "vqtouch.plugins.data.readers.tvl_plugin",
        build_tvl_hct,
        {"split": "test", "runs": ["data1", "data2"]},
        3,
        lambda root: root / "data2" / "test.csv",
        _empty_hct,
    ),
    ReaderCase(
        "tvl_ssvtp",
        "vqtouch.plugins.data.readers.tvl_plugin",
        build_tvl_ssvtp,
        {"split": "test"},
        2,
        lambda root: root / "test.csv",
        _empty_list("test.csv"),
    ),
    ReaderCase(
        "objectfolder_real",
        "vqtouch.plugins.data.readers.objectfolder_plugin",
        build_objectfolder_real,
        {},
        7,
        None,
        _empty_objectfolder_real,
    ),
    ReaderCase(
        "objectfolder_cross",
        "vqtouch.plugins.data.readers.objectfolder_plugin",
        build_objectfolder_cross,
        {"split": "train"},
        4,
        lambda root: root / "split.json",
        _empty_objectfolder_cross,
    ),
    ReaderCase(
        "fabricvst", "vqtouch.plugins.data.readers.fabricvst_plugin", build_fabricvst, {}, 4, None, _empty_fabricvst
    ),
    ReaderCase(
        "image_folder",
        "vqtouch.plugins.data.readers.image_folder_plugin",
        lambda root: build_image_folder(root) / "classes",
        {},
        3,
        None,
        _empty_image_folder,
    ),
]

"""Dataset readers: every public layout rebuilt in miniature and read through the plugin system.

Fixture images are flat colours that encode a sample number and a modality (see
``tests/dataset_fixtures.py``), so pairing, order and split selection are checked from pixels,
not just from shapes.
"""

from __future__ import annotations

import json
import os
import pickle
import re
import shutil
import time
import warnings
from pathlib import Path

import pytest
import torch

from vqtouch.core import ConfigError, DatasetError, TactileDataset, load_plugins
from vqtouch.plugins.data.readers import _headers
from vqtouch.plugins.data.readers._io import ImageLoader, SkippedSamplesWarning


import dataset_fixtures as layouts  # noqa: E402  (registered by conftest)

CASES = layouts.READER_CASES
HOST = load_plugins(autoload=False, extra=sorted({case.module for case in CASES}))
SIZE = 16


def test_the_readers_crop_modes_are_the_image_loaders():
    from typing import get_args

    from vqtouch.plugins.utils.images import CropMode
    from vqtouch.plugins.data.readers import _options

    assert get_args(_options.CropMode) == get_args(CropMode)


@pytest.fixture(autouse=True)
def _own_cache_folder(tmp_path_factory, monkeypatch) -> Path:
    """Each test gets its own user cache folder, so no test reads or writes ~/.cache."""
    folder = tmp_path_factory.mktemp("xdg_cache")
    monkeypatch.setenv("XDG_CACHE_HOME", str(folder))
    return folder


def build(config: dict):
    """Build a dataset exactly as users do: through the plugin host."""
    return HOST.build("dataset", config)


def build_lenient(config: dict):
    """Build with lenient=True; returns the dataset and the one skip warning it must emit."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        dataset = build({**config, "lenient": True})
    skip_warnings = [w for w in caught if issubclass(w.category, SkippedSamplesWarning)]
    assert len(skip_warnings) == 1, [str(w.message) for w in caught]
    return dataset, str(skip_warnings[0].message)


def build_case(case, tmp_path: Path, **extra):
    root = case.build(tmp_path / "data")
    return root, build(case.config(root, **extra))


def check_contract(sample: dict, visual: bool) -> None:
    """The sample dict contract of vqtouch.core.TactileDataset."""
    assert set(sample) == {"tactile", "label", "text", "sensor", "id"} | ({"visual"} if visual else set())
    for key in ("tactile", "visual") if visual else ("tactile",):
        image = sample[key]
        assert image.shape == (3, SIZE, SIZE) and image.dtype == torch.float32
        assert float(image.min()) >= 0.0 and float(image.max()) <= 1.0
    assert type(sample["label"]) is int and isinstance(sample["text"], str)
    assert isinstance(sample["sensor"], str) and sample["sensor"] and isinstance(sample["id"], str) and sample["id"]


def check_pair(sample: dict, number: int) -> None:
    """The tactile (and visual) image of ``sample`` were written for sample ``number``."""
    assert layouts.sample_number(sample["tactile"]) == number
    assert layouts.modality(sample["tactile"]) == "tactile"
    if "visual" in sample:
        assert layouts.sample_number(sample["visual"]) == number
        assert layouts.modality(sample["visual"]) == "visual"


def numbers_of(dataset) -> list[int]:
    return [layouts.sample_number(dataset[index]["tactile"]) for index in range(len(dataset))]


def first_file(dataset, kind: str = "tactile") -> Path:
    return dataset.base / getattr(dataset.records[0], kind)


# ============================================================================================
# Every reader
# ============================================================================================
@pytest.mark.parametrize("case", CASES, ids=lambda case: case.name)
def test_reader_follows_the_sample_contract(case, tmp_path):
    _, dataset = build_case(case, tmp_path)
    assert isinstance(dataset, TactileDataset) and len(dataset) == case.length
    for index in range(len(dataset)):
        check_contract(dataset[index], visual=dataset.has_visual)
    assert len({dataset[index]["id"] for index in range(len(dataset))}) == len(dataset)
    batch = next(iter(torch.utils.data.DataLoader(dataset, batch_size=2)))
    assert batch["tactile"].shape == (2, 3, SIZE, SIZE) and len(batch["id"]) == 2


@pytest.mark.parametrize("case", CASES, ids=lambda case: case.name)
def test_reader_config_is_strict_and_complete(case, tmp_path):
    with pytest.raises(ConfigError, match="bogus_option"):
        HOST.build("dataset", {"name": case.name, "root": str(tmp_path), "bogus_option": 1})
    model = HOST.registry("dataset").get(case.name).config_model
    assert model.model_config.get("extra") == "forbid" and model.model_config.get("frozen") is True
    assert not [field for field, info in model.model_fields.items() if not info.description]
    assert HOST.validate("dataset", {"name": case.name}).name == case.name  # every option has a default
    with pytest.raises(ConfigError, match="image_size"):
        HOST.build("dataset", {"name": case.name, "root": str(tmp_path), "image_size": 2})


@pytest.mark.parametrize("case", CASES, ids=lambda case: case.name)
def test_unset_or_missing_root_is_a_clear_error(case, tmp_path):
    with pytest.raises(DatasetError, match="root="):
        build({"name": case.name})
    missing = tmp_path / "nowhere"
    with pytest.raises(DatasetError, match=f"{missing}.*does not exist"):
        build({"name": case.name, "root": str(missing)})


@pytest.mark.parametrize("case", [case for case in CASES if case.list_file], ids=lambda case: case.name)
def test_missing_list_file_is_named(case, tmp_path):
    root = case.build(tmp_path / "data")
    list_file = case.list_file(root)
    list_file.unlink()
    with pytest.raises(DatasetError, match=f"missing .*{list_file}"):
        build(case.config(root))


MISSING_FOLDERS = [  # (reader, folder to remove relative to the dataset root, expected message)
    ("touch_and_go", "dataset", "missing frames .* folder: {path}"),
    ("tvl_hct", "data2", "missing collection run 'data2' folder: {path}"),
    ("objectfolder_real", "2/tactile_data", "object 2: missing folder {path}"),
    ("fabricvst", "tactile", "missing tactile image folder: {path}"),
    ("fabricvst", "visual_cropped", "is flat, so fabric names come from the folders of {path}, which is missing"),
]


@pytest.mark.parametrize("name, folder, message", MISSING_FOLDERS)
def test_missing_folder_is_named(name, folder, message, tmp_path):
    case = next(case for case in CASES if case.name == name)
    root = case.build(tmp_path / "data")
    if folder == "visual_cropped":  # only the flat tactile layout needs it
        root = layouts.build_fabricvst(tmp_path / "flat", flat=True)
    shutil.rmtree(root / folder)
    with pytest.raises(DatasetError, match=message.format(path=root / folder)):
        build(case.config(root))


@pytest.mark.parametrize("case", CASES, ids=lambda case: case.name)
@pytest.mark.parametrize("lenient", [False, True])
def test_empty_split_is_an_error(case, lenient, tmp_path):
    root = case.build(tmp_path / "data")
    case.empty_split(root)
    with pytest.raises(DatasetError, match="empty"):
        build(case.config(root, lenient=lenient))


@pytest.mark.parametrize(
    "case",
    [case for case in CASES if case.name not in {"objectfolder_real", "fabricvst", "image_folder"}],
    ids=lambda case: case.name,
)
def test_pair_with_missing_visual_fails_or_is_skipped(case, tmp_path):
    root, dataset = build_case(case, tmp_path)
    victim = first_file(dataset, "visual")
    victim.unlink()
    with pytest.raises(DatasetError, match=f"missing .*{victim}"):
        build(case.config(root))
    lenient, message = build_lenient(case.config(root))
    assert len(lenient) == case.length - 1 and "skipped 1 bad sample" in message and str(victim) in message


BAD_FILES = {  # damage -> (how to damage the file, the strict error; {path} is the escaped file name)
    "not_an_image": (
        lambda path: path.write_bytes(b"definitely not an image"),
        r"cannot read image {path}: not an image file Pillow can read",
    ),
    "empty": (lambda path: path.write_bytes(b""), r"cannot read image {path}: not an image file Pillow can read"),
    "broken_link": (layouts.break_link, r"image {path} is a broken symbolic link to .*\.gone; fix or remove it"),
    "animated_gif": (
        lambda path: layouts.write_frames(path, "GIF"),
        r"image {path} has 2 frames \(GIF\); expected a single still image: save one frame of it",
    ),
    "animated_png": (
        lambda path: layouts.write_frames(path, "PNG"),
        r"image {path} has 2 frames \(PNG\); expected a single still image: save one frame of it",
    ),
    "multipage_tiff": (
        lambda path: layouts.write_frames(path, "TIFF", count=3),
        r"image {path} has 3 frames \(TIFF\); expected a single still image: save one frame of it",
    ),
    "16_bit": (layouts.write_16_bit, r"image {path} has unsupported mode I;16; expected 8-bit RGB"),
}


@pytest.mark.parametrize("case", CASES, ids=lambda case: case.name)
@pytest.mark.parametrize("damage", sorted(BAD_FILES))
def test_bad_image_file_fails_at_build_or_is_skipped(case, damage, tmp_path):
    """Every listed image's header is opened when the reader is built, so strict runs fail in seconds."""
    root, dataset = build_case(case, tmp_path)
    victim = first_file(dataset)
    damage_file, expected = BAD_FILES[damage]
    damage_file(victim)
    with pytest.raises(DatasetError, match=expected.format(path=re.escape(str(victim)))) as failure:
        build(case.config(root))
    assert "\n" not in str(failure.value) and "set lenient=true" in str(failure.value)
    with pytest.raises(DatasetError, match=expected.format(path=re.escape(str(victim)))):
        build(case.config(root, header_cache=False))
    lenient, message = build_lenient(case.config(root))
    assert len(lenient) == case.length - 1 and "skipped 1 bad sample" in message and str(victim) in message
    assert all(dataset.records[0].id != record.id for record in lenient.records)


@pytest.mark.parametrize("case", CASES, ids=lambda case: case.name)
def test_truncated_image_fails_on_access_or_is_skipped(case, tmp_path):
    root, dataset = build_case(case, tmp_path)
    victim = first_file(dataset)
    layouts.truncate_pixels(victim)
    strict = build(case.config(root))
    assert len(strict) == case.length  # the header is intact: only decoding the pixels finds the damage
    with pytest.raises(DatasetError, match=f"cannot decode image {victim}"):
        strict[0]
    lenient, message = build_lenient(case.config(root))
    assert len(lenient) == case.length - 1 and "skipped 1 bad sample" in message and str(victim) in message
    assert all(dataset.records[0].id != record.id for record in lenient.records)


@pytest.mark.parametrize("case", CASES, ids=lambda case: case.name)
def test_greyscale_image_is_an_error_unless_allowed(case, tmp_path):
    root, dataset = build_case(case, tmp_path)
    victim = first_file(dataset)
    layouts.write_image(victim, (90, 90, 90), mode="L")
    with pytest.raises(DatasetError, match=f"{victim} is greyscale.*allow_greyscale"):
        build(case.config(root))  # found by the header check, before any sample is loaded
    grey = build(case.config(root, allow_greyscale=True))[0]["tactile"]
    assert torch.equal(grey[0], grey[1]) and torch.equal(grey[1], grey[2])
    assert abs(float(grey.mean()) - 90 / 255) < 3 / 255
    lenient, message = build_lenient(case.config(root))
    assert len(lenient) == case.length - 1 and "greyscale" in message


def test_header_check_stops_at_max_samples(tmp_path):
    """Like the list checks, the header check covers only the samples kept, in list order."""
    root = layouts.build_touch_and_go(tmp_path)
    train_list = root / "dataset" / "train.txt"
    train_list.write_text(train_list.read_text() + "not a list line\n")
    recording, frame = layouts.tag_key(3).split("/")
    (root / "dataset" / recording / "gelsight_frame" / frame).write_bytes(b"not an image")
    assert len(build(tag_config(root, max_samples=2))) == 2
    with pytest.raises(DatasetError, match="cannot read image"):
        build(tag_config(root, max_samples=3))


@pytest.mark.parametrize(
    "case",
    [
        case
        for case in CASES
        if case.name in {"visgel", "objectfolder_real", "objectfolder_cross", "fabricvst", "image_folder"}
    ],
    ids=lambda case: case.name,
)
def test_rgba_is_accepted_only_when_opaque(case, tmp_path):
    root, dataset = build_case(case, tmp_path)
    victim = first_file(dataset)
    expected = dataset[0]["tactile"]
    rgb = tuple(round(float(value) * 255) for value in expected.mean(dim=(1, 2)))
    layouts.write_image(victim, rgb, mode="RGBA", alpha=255)
    assert torch.allclose(build(case.config(root))[0]["tactile"], expected)
    layouts.write_image(victim, rgb, mode="RGBA", alpha=128)
    with pytest.raises(DatasetError, match=f"{victim} has transparent pixels"):
        build(case.config(root))[0]
    lenient, message = build_lenient(case.config(root))
    assert len(lenient) == case.length - 1 and "transparent" in message


@pytest.mark.parametrize("case", CASES, ids=lambda case: case.name)
def test_max_samples_keeps_the_first_samples(case, tmp_path):
    root, dataset = build_case(case, tmp_path)
    limited = build(case.config(root, max_samples=2))
    assert [record.id for record in limited.records] == [record.id for record in dataset.records[:2]]


def test_datasets_pickle_for_dataloader_workers(tmp_path):
    _, dataset = build_case(CASES[1], tmp_path, subtract_reference=True)
    expected = dataset[0]
    copy = pickle.loads(pickle.dumps(dataset))
    assert torch.equal(copy[0]["tactile"], expected["tactile"]) and copy[0]["id"] == expected["id"]


# ============================================================================================
# Image decoding
# ============================================================================================
@pytest.mark.parametrize("crop, white_fraction", [("center", 0.0), ("top", 0.5), ("stretch", 0.25)])
def test_crop_modes(crop, white_fraction, tmp_path):
    from PIL import Image

    image = Image.new("RGB", (20, 40), (0, 0, 0))
    image.paste((255, 255, 255), (0, 0, 20, 10))  # the top quarter is white
    image.save(tmp_path / "tall.png")
    loaded = ImageLoader(size=SIZE, crop=crop).load(tmp_path / "tall.png")
    assert loaded.shape == (3, SIZE, SIZE)
    assert abs(float(loaded.mean()) - white_fraction) < 0.05


# ============================================================================================
# Header check cache
# ============================================================================================
@pytest.fixture
def header_opens(monkeypatch) -> list[Path]:
    """The files that Pillow opens from now on, in any thread; and files count as settled at once."""
    from PIL import Image

    opened: list[Path] = []
    real_open = Image.open

    def counting_open(path, *args, **kwargs):
        opened.append(Path(path))
        return real_open(path, *args, **kwargs)

    monkeypatch.setattr(Image, "open", counting_open)
    # Fixture files are seconds old; the real settle time would keep them all out of the cache.
    monkeypatch.setattr(_headers, "HEADER_CACHE_SETTLE_NS", 0)
    return opened


def cache_files(folder: Path) -> list[Path]:
    return sorted((folder / "vqtouch" / "image_headers").glob("*"))


def test_header_cache_skips_unchanged_files(tmp_path, header_opens, _own_cache_folder):
    root = layouts.build_touch_and_go(tmp_path)
    first = build(tag_config(root))
    files = {first.base / path for record in first.records for path in (record.tactile, record.visual)}
    assert set(header_opens) == files and len(header_opens) == len(files)  # each header once
    [cache] = cache_files(_own_cache_folder)
    assert cache.suffix == ".json" and json.loads(cache.read_text())["base"] == str(root)
    header_opens.clear()
    written = cache.stat()
    second = build(tag_config(root))
    assert header_opens == [] and second.records == first.records
    assert (cache.stat().st_ino, cache.stat().st_mtime_ns) == (written.st_ino, written.st_mtime_ns)  # not rewritten
    build(tag_config(root, split="test"))  # another split of the same folder shares the cache file
    assert len(header_opens) == 4 and len(cache_files(_own_cache_folder)) == 1
    header_opens.clear()
    assert len(build(tag_config(root, split="all"))) == 5 and header_opens == []


def rewrite_keeping_size_and_mtime(path: Path, data: bytes) -> None:
    """Replace a file's bytes without changing its size or modification time (as ``cp -p`` can)."""
    before = path.stat()
    assert len(data) == before.st_size
    for _ in range(200):  # the change time ticks coarsely: wait until it moves
        path.write_bytes(data)
        os.utime(path, ns=(before.st_atime_ns, before.st_mtime_ns))
        if path.stat().st_ctime_ns != before.st_ctime_ns:
            return
        time.sleep(0.005)
    raise AssertionError(f"the change time of {path} did not move")


def test_header_cache_never_hides_a_changed_file(tmp_path, header_opens):
    root = layouts.build_touch_and_go(tmp_path)
    victim = first_file(build(tag_config(root)))
    rewrite_keeping_size_and_mtime(victim, b"x" * victim.stat().st_size)
    with pytest.raises(DatasetError, match=f"cannot read image {re.escape(str(victim))}"):
        build(tag_config(root))
    layouts.write_image(victim, (90, 90, 90), mode="L")  # a new size and time
    with pytest.raises(DatasetError, match=f"{re.escape(str(victim))} is greyscale"):
        build(tag_config(root))
    assert len(build(tag_config(root, allow_greyscale=True))) == 3  # the cache keeps facts, not verdicts
    header_opens.clear()
    with pytest.raises(DatasetError, match=f"{re.escape(str(victim))} is greyscale"):
        build(tag_config(root))
    assert header_opens == []  # the greyscale verdict came from the cached header


def test_files_changed_just_before_the_check_are_not_cached(tmp_path, _own_cache_folder):
    """A file checked within the clock's resolution of its last change could change again unseen."""
    root = layouts.build_touch_and_go(tmp_path)
    build(tag_config(root))  # every fixture file is younger than HEADER_CACHE_SETTLE_NS
    assert cache_files(_own_cache_folder) == []


def test_header_cache_folder_follows_xdg(tmp_path, header_opens, monkeypatch):
    root = layouts.build_touch_and_go(tmp_path / "data")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    build(tag_config(root))
    assert len(cache_files(tmp_path / "xdg")) == 1
    monkeypatch.setenv("XDG_CACHE_HOME", "relative/xdg")  # ignored, as the XDG specification says
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    build(tag_config(root))
    assert len(cache_files(tmp_path / "home" / ".cache")) == 1 and not Path("relative").exists()


def test_header_cache_can_be_turned_off(tmp_path, header_opens, _own_cache_folder):
    root = layouts.build_touch_and_go(tmp_path)
    build(tag_config(root, header_cache=False))
    build(tag_config(root, header_cache=False))
    assert len(header_opens) == 12 and cache_files(_own_cache_folder) == []


def test_header_cache_is_written_atomically_and_damage_is_ignored(
    tmp_path, header_opens, _own_cache_folder, monkeypatch
):
    root = layouts.build_touch_and_go(tmp_path)
    build(tag_config(root))
    [cache] = cache_files(_own_cache_folder)
    saved = cache.read_bytes()

    def failing_replace(source, target):
        raise OSError("disk full")

    with monkeypatch.context() as patch:  # the new cache is written aside, then fails to take its place
        patch.setattr(os, "replace", failing_replace)
        assert len(build(tag_config(root, split="test"))) == 2  # a cache that cannot be saved is no error
    assert cache_files(_own_cache_folder) == [cache] and cache.read_bytes() == saved
    cache.write_text('{"version": 1, "base": "trunc')
    header_opens.clear()
    assert len(build(tag_config(root))) == 3 and len(header_opens) == 6
    assert json.loads(cache.read_text())["base"] == str(root)  # rewritten whole


# ============================================================================================
# Touch and Go
# ============================================================================================
def tag_config(root: Path, **options) -> dict:
    return {"name": "touch_and_go", "root": str(root), "image_size": SIZE, **options}


def test_touch_and_go_pairs_frames_labels_and_drops_inconclusive(tmp_path):
    root = layouts.build_touch_and_go(tmp_path)
    dataset = build(tag_config(root))
    expected = [(number, label) for number, label in layouts.TAG_LISTS["train"] if label != -1]
    assert len(dataset) == len(expected) and dataset.dropped_unlabelled == 1
    assert dataset.class_names == layouts.TAG_CLASSES and dataset.num_classes == 20
    assert dataset.class_names[-1] == "Others (foam: soft)"
    for index, (number, label) in enumerate(expected):
        sample = dataset[index]
        check_contract(sample, visual=True)
        check_pair(sample, number)
        assert sample["label"] == label and sample["id"] == layouts.tag_key(number)
        assert sample["sensor"] == "gelsight" and sample["text"] == ""


def test_touch_and_go_split_and_label_options(tmp_path):
    root = layouts.build_touch_and_go(tmp_path)
    test = build(tag_config(root, split="test"))
    assert numbers_of(test) == [4, 5] and [record.label for record in test.records] == [0, 19]
    assert len(build(tag_config(root, split="all"))) == 5  # label.txt, without the -1 line
    hard_soft = build(tag_config(root, labels="hard_soft"))
    assert hard_soft.class_names == ["hard", "soft"]
    assert [record.label for record in hard_soft.records] == [1, 0, 1]  # fabric 8, wood 3, grass 13
    rough = build(tag_config(root, split="train_rough"))
    assert rough.class_names == ["rough_smooth_0", "rough_smooth_1"]
    assert numbers_of(rough) == [0, 1] and [record.label for record in rough.records] == [1, 0]
    with pytest.raises(ConfigError, match="hard_soft"):
        build(tag_config(root, split="test_rough", labels="hard_soft"))


def test_touch_and_go_label_outside_category_reference(tmp_path):
    root = layouts.build_touch_and_go(tmp_path)
    train_list = root / "dataset" / "train.txt"
    with train_list.open("a") as handle:
        handle.write(layouts.tag_line(5, 25) + "\n")
    with pytest.raises(DatasetError, match=rf"{train_list} line 5: label 25 is not a class of .*category_reference"):
        build(tag_config(root))
    dataset, message = build_lenient(tag_config(root))
    assert len(dataset) == 3 and "skipped 1 bad sample" in message and "line 5" in message


def test_touch_and_go_bad_lines_and_category_file(tmp_path):
    root = layouts.build_touch_and_go(tmp_path)
    train_list = root / "dataset" / "train.txt"
    train_list.write_text(train_list.read_text() + "not a list line\n" + layouts.tag_line(4, 0) + "\n")
    (root / "dataset" / layouts.TAG_RECORDINGS[0] / "gelsight_frame" / "0000000004.jpg").unlink()
    with pytest.raises(DatasetError, match="line 5: expected '<recording>/<frame>.jpg,<label>'"):
        build(tag_config(root))
    dataset, message = build_lenient(tag_config(root))
    assert len(dataset) == 3 and "skipped 2 bad sample" in message and "tactile frame" in message
    categories = root / "category_reference.txt"
    categories.write_text(categories.read_text() + "Mystery\n")
    with pytest.raises(DatasetError, match=rf"{categories} line 22: expected '<Name>: <id>'"):
        build(tag_config(root))


# ============================================================================================
# VisGel
# ============================================================================================
@pytest.mark.parametrize("direction", ["vision2touch", "touch2vision"])
def test_visgel_pairs_source_and_destination(direction, tmp_path):
    root = layouts.build_visgel(tmp_path)
    dataset = build({"name": "visgel", "root": str(root), "image_size": SIZE, "direction": direction})
    assert len(dataset) == 3 and dataset.class_names == []
    for index, number in enumerate(layouts.VISGEL_NUMBERS):
        sample = dataset[index]
        check_pair(sample, number)
        assert sample["id"] == layouts.visgel_frame(number, "tactile")
        assert (sample["label"], sample["text"], sample["sensor"]) == (-1, "", "gelsight")
    assert len(build({"name": "visgel", "root": str(root), "split": "eval", "direction": direction})) == 1


@pytest.mark.parametrize("direction", ["vision2touch", "touch2vision"])
def test_visgel_subtracts_the_tactile_reference_frame(direction, tmp_path):
    root = layouts.build_visgel(tmp_path)
    dataset = build(
        {"name": "visgel", "root": str(root), "image_size": SIZE, "direction": direction, "subtract_reference": True}
    )
    tactile = torch.tensor(layouts.colour(1, "tactile"), dtype=torch.float32)
    expected = ((tactile - torch.tensor(layouts.REFERENCE_COLOUR)) / 255 + 0.5).clamp(0, 1)
    assert torch.allclose(dataset[0]["tactile"].mean(dim=(1, 2)), expected, atol=1.5 / 255)
    assert layouts.sample_number(dataset[0]["visual"]) == 1  # the visual image is left alone


def test_visgel_line_with_wrong_path_count(tmp_path):
    root = layouts.build_visgel(tmp_path)
    list_file = root / "data_lst" / "train_vision2touch.txt"
    with list_file.open("a") as handle:
        handle.write(" ".join(["data_seen/x.png"] * 7) + "\n")
    with pytest.raises(DatasetError, match=f"{list_file} line 4: expected 8 space-separated paths, got 7"):
        build({"name": "visgel", "root": str(root)})
    dataset, message = build_lenient({"name": "visgel", "root": str(root)})
    assert len(dataset) == 3 and "skipped 1 bad sample" in message


# ============================================================================================
# TVL HCT
# ============================================================================================
def hct_config(root: Path, **options) -> dict:
    return {"name": "tvl_hct", "root": str(root), "image_size": SIZE, "runs": ["data1", "data2"], **options}


def test_tvl_hct_test_split_pairs_frames_with_captions(tmp_path):
    root = layouts.build_tvl_hct(tmp_path)
    dataset = build(hct_config(root, split="test"))
    assert numbers_of(dataset) == [11, 12, 13]
    for index, (run, number) in enumerate([("data1", 11), ("data1", 12), ("data2", 13)]):
        sample = dataset[index]
        check_pair(sample, number)
        assert sample["text"] == layouts.hct_caption(number) and sample["sensor"] == "digit"
        assert sample["id"] == f"{run}/{layouts.hct_paths(number)[1]}" and sample["label"] == -1


def test_tvl_hct_train_and_val_are_tvls_split(tmp_path):
    from sklearn.model_selection import train_test_split

    root = layouts.build_tvl_hct(tmp_path)
    listed = [number for run in layouts.HCT_RUNS.values() for number in run["train"]]
    expected_train, expected_val = train_test_split(listed, train_size=0.9, random_state=42)
    train, val = build(hct_config(root, split="train")), build(hct_config(root, split="val"))
    assert numbers_of(train) == expected_train and numbers_of(val) == expected_val
    assert sorted(numbers_of(train) + numbers_of(val)) == numbers_of(build(hct_config(root, split="trainval")))
    assert len(build(hct_config(root, split="trainval", runs=["data2"]))) == 5


def test_tvl_hct_contact_json_source(tmp_path):
    root = layouts.build_tvl_hct(tmp_path)
    dataset = build(hct_config(root, split="trainval", source="contact_json"))
    assert sorted(numbers_of(dataset)) == list(range(14)) and {record.text for record in dataset.records} == {""}
    with pytest.raises(DatasetError, match="contact.json has no test split"):
        build(hct_config(root, split="test", source="contact_json"))
    contact = root / "data2" / "contact.json"
    lists = json.loads(contact.read_text())
    lists["tactile"].pop()
    contact.write_text(json.dumps(lists))
    for lenient in (False, True):  # no pairing of unequal lists is trustworthy, lenient or not
        with pytest.raises(DatasetError, match=f"{contact}: the parallel lists have different lengths"):
            build(hct_config(root, split="trainval", source="contact_json", lenient=lenient))


def test_tvl_hct_row_pairing_different_frames_is_refused(tmp_path):
    root = layouts.build_tvl_hct(tmp_path)
    test_csv = root / "data1" / "test.csv"
    vision_11, _, background_11 = layouts.hct_paths(11)
    tactile_12 = layouts.hct_paths(12)[1]
    test_csv.write_text(test_csv.read_text() + f"{vision_11},{tactile_12},{background_11},mismatched\n")
    with pytest.raises(DatasetError, match=f"{test_csv} line 4: vision .* and tactile .* are not the same frame"):
        build(hct_config(root, split="test"))
    dataset, message = build_lenient(hct_config(root, split="test"))
    assert numbers_of(dataset) == [11, 12, 13] and "not the same frame" in message


def test_tvl_hct_swapped_folders_are_flagged_not_fixed(tmp_path):
    root = layouts.build_tvl_hct(tmp_path)
    vision, tactile, _ = (root / "data1" / path for path in layouts.hct_paths(12))
    vision_bytes = vision.read_bytes()
    vision.write_bytes(tactile.read_bytes())
    tactile.write_bytes(vision_bytes)
    unchecked = build(hct_config(root, split="test"))
    assert layouts.modality(unchecked[1]["tactile"]) == "visual"  # nothing is silently "fixed"
    with pytest.raises(DatasetError, match=f"tactile image {tactile} .* look swapped"):
        build(hct_config(root, split="test", check_swap=True))
    dataset, message = build_lenient(hct_config(root, split="test", check_swap=True))
    assert numbers_of(dataset) == [11, 13] and "swapped" in message


def test_tvl_hct_background_subtraction(tmp_path):
    root = layouts.build_tvl_hct(tmp_path)
    dataset = build(hct_config(root, split="test", subtract_background=True))
    tactile = torch.tensor(layouts.colour(11, "tactile"), dtype=torch.float32)
    expected = ((tactile - torch.tensor(layouts.REFERENCE_COLOUR)) / 255 + 0.5).clamp(0, 1)
    assert torch.allclose(dataset[0]["tactile"].mean(dim=(1, 2)), expected, atol=3 / 255)
    (root / "data1" / layouts.hct_paths(11)[2]).unlink()
    with pytest.raises(DatasetError, match="missing background image"):
        build(hct_config(root, split="test", subtract_background=True))


# ============================================================================================
# TVL SSVTP
# ============================================================================================
def ssvtp_config(root: Path, **options) -> dict:
    return {"name": "tvl_ssvtp", "root": str(root), "image_size": SIZE, **options}


def test_tvl_ssvtp_pairs_by_index_with_adjectives(tmp_path):
    root = layouts.build_tvl_ssvtp(tmp_path)
    test = build(ssvtp_config(root, split="test"))  # test.csv has no header row
    for index, number in enumerate(layouts.SSVTP_TEST):
        sample = test[index]
        check_pair(sample, number)
        assert sample["text"] == f"smooth, hard, grade{number}" and sample["sensor"] == "digit"
        assert sample["id"] == f"images_tac/image_{number}_tac.jpg"
    train, val = build(ssvtp_config(root)), build(ssvtp_config(root, split="val"))
    assert (len(train), len(val)) == (10, 2)
    assert sorted(numbers_of(train) + numbers_of(val)) == numbers_of(build(ssvtp_config(root, split="trainval")))


def test_tvl_ssvtp_mismatched_index_and_missing_text(tmp_path):
    root = layouts.build_tvl_ssvtp(tmp_path)
    tactile_21 = root / "images_tac" / "image_21_tac.jpg"
    tactile_21.rename(root / "images_tac" / "image_22_tac.jpg")
    (root / "text" / "labels_20.txt").unlink()
    with pytest.raises(DatasetError, match=f"missing adjective file {root / 'text' / 'labels_20.txt'}"):
        build(ssvtp_config(root, split="test", max_samples=1))
    (root / "test.csv").write_text("images_rgb/image_21_rgb.jpg\n")
    with pytest.raises(DatasetError, match=f"line 1: missing tactile image {tactile_21}"):
        build(ssvtp_config(root, split="test"))


# ============================================================================================
# ObjectFolder
# ============================================================================================
def test_objectfolder_real_walks_objects_and_labels_by_material(tmp_path):
    root = layouts.build_objectfolder_real(tmp_path)
    dataset = build({"name": "objectfolder_real", "root": str(root), "image_size": SIZE})
    frames = layouts.of_real_frames()
    assert len(dataset) == len(frames) and dataset.class_names == ["Ceramic", "Steel"] and not dataset.has_visual
    for index, (obj, trial, frame, number) in enumerate(frames):
        sample = dataset[index]
        check_pair(sample, number)
        assert sample["id"] == f"{obj}/tactile_data/{trial}/0/gelsight/{frame}.png"
        assert sample["label"] == dataset.class_names.index(layouts.OF_REAL_MATERIALS[obj])
        assert sample["sensor"] == "gelsight" and "visual" not in sample
    chosen = build({"name": "objectfolder_real", "root": str(root), "objects": [3, 1]})
    assert [record.id.split("/")[0] for record in chosen.records] == ["3", "3", "1", "1", "1"]


def test_objectfolder_real_metadata_is_optional_but_must_cover_every_object(tmp_path):
    root = layouts.build_objectfolder_real(tmp_path, metadata=False)
    unlabelled = build({"name": "objectfolder_real", "root": str(root)})
    assert unlabelled.class_names == [] and {record.label for record in unlabelled.records} == {-1}
    metadata = layouts.write_text(tmp_path / "meta.csv", "Index,Name,Material\n1,bowl,Ceramic\n2,spoon,Steel\n")
    config = {"name": "objectfolder_real", "root": str(root), "metadata_csv": str(metadata)}
    with pytest.raises(DatasetError, match=f"object 3 .* has no row in {metadata}"):
        build(config)
    dataset, message = build_lenient(config)
    assert len(dataset) == 5 and "skipped 2 bad sample" in message and "2 frames" in message
    with pytest.raises(DatasetError, match=r"no folder for object\(s\) \[4\]"):
        build({**config, "objects": [4]})
    bad_metadata = layouts.write_text(tmp_path / "bad.csv", "Index,Material\n1,Ceramic\n")
    with pytest.raises(DatasetError, match="Index, Name, Material"):
        build({**config, "metadata_csv": str(bad_metadata)})


def test_objectfolder_real_trial_without_gelsight_folder(tmp_path):
    root = layouts.build_objectfolder_real(tmp_path)
    (root / "2" / "tactile_data" / "5").mkdir()
    with pytest.raises(DatasetError, match="object 2 trial 5: missing folder"):
        build({"name": "objectfolder_real", "root": str(root)})


def cross_config(root: Path, **options) -> dict:
    return {"name": "objectfolder_cross", "root": str(root), "image_size": SIZE, **options}


def test_objectfolder_cross_pairs_contacts_and_labels_objects(tmp_path):
    root = layouts.build_objectfolder_cross(tmp_path)
    train = build(cross_config(root))
    assert train.class_names == ["1", "2", "3", "10"]  # every object of the split file, natural order
    for index, (obj, contact) in enumerate(layouts.OF_CROSS_SPLITS["train"]):
        sample = train[index]
        check_pair(sample, layouts.of_cross_number(obj, contact))
        assert sample["label"] == train.class_names.index(str(obj)) and sample["id"] == f"touch/{obj}/{contact}.png"
    test = build(cross_config(root, split="test"))
    assert [record.label for record in test.records] == [1, 3] and len(build(cross_config(root, split="val"))) == 1
    reference = build(cross_config(root, subtract_reference=True))[0]["tactile"].mean(dim=(1, 2))
    tactile = torch.tensor(layouts.colour(1, "tactile"), dtype=torch.float32)
    expected = ((tactile - torch.tensor(layouts.REFERENCE_COLOUR)) / 255 + 0.5).clamp(0, 1)
    assert torch.allclose(reference, expected, atol=1.5 / 255)


def test_objectfolder_cross_malformed_entries_and_splits(tmp_path):
    root = layouts.build_objectfolder_cross(tmp_path)
    split_file = root / "split.json"
    split_file.write_text(json.dumps({**layouts.OF_CROSS_SPLITS, "train": [*layouts.OF_CROSS_SPLITS["train"], [1]]}))
    with pytest.raises(DatasetError, match=rf"{split_file} train\[4\]: expected \[object, contact\]"):
        build(cross_config(root))
    dataset, message = build_lenient(cross_config(root))
    assert len(dataset) == 4 and "skipped 1 bad sample" in message
    split_file.write_text(json.dumps({"train": layouts.OF_CROSS_SPLITS["train"]}))
    with pytest.raises(DatasetError, match="has no 'val' list"):
        build(cross_config(root, split="val"))
    split_file.write_text("{not json")
    with pytest.raises(DatasetError, match=f"malformed JSON {split_file} line 1"):
        build(cross_config(root))


# ============================================================================================
# FabricVST
# ============================================================================================
def fabric_config(root: Path, **options) -> dict:
    return {"name": "fabricvst", "root": str(root), "image_size": SIZE, **options}


EXPECTED_FABRIC_TEXT = {"Material_1": "soft", "Material_10": "rough, shinny", "Material_2": "rough"}


@pytest.mark.parametrize("flat", [False, True])
def test_fabricvst_labels_by_sorted_fabric_with_majority_attributes(flat, tmp_path):
    root = layouts.build_fabricvst(tmp_path, flat=flat)
    csvs = [f"annotator_{index}.csv" for index in range(3)]
    dataset = build(fabric_config(root, attribute_csvs=csvs))
    assert dataset.class_names == ["Material_1", "Material_10", "Material_2"]
    expected = [(fabric, number) for fabric in dataset.class_names for number in layouts.fabric_numbers()[fabric]]
    assert len(dataset) == len(expected) and not dataset.has_visual
    for index, (fabric, number) in enumerate(expected):
        sample = dataset[index]
        check_pair(sample, number)
        assert sample["label"] == dataset.class_names.index(fabric) and sample["text"] == EXPECTED_FABRIC_TEXT[fabric]
        assert sample["sensor"] == "fabricvst" and sample["id"].startswith("tactile/")
    only = build(fabric_config(root, fabrics=["Material_2"], sensor="gelsight_mini"))
    assert [record.label for record in only.records] == [2] and only[0]["sensor"] == "gelsight_mini"
    assert only[0]["text"] == ""  # attributes only when the annotator CSVs are named


def test_fabricvst_unrecognised_layouts_fail_clearly(tmp_path):
    root = layouts.build_fabricvst(tmp_path, flat=True)
    stray = layouts.write_sample(root / "tactile" / "Velvet_0.png", 0, "tactile")
    with pytest.raises(DatasetError, match=f"{stray} does not start with a fabric name"):
        build(fabric_config(root))
    dataset, message = build_lenient(fabric_config(root))
    assert len(dataset) == 4 and "skipped 1 bad sample" in message
    (root / "tactile" / "Material_1").mkdir()
    with pytest.raises(DatasetError, match="holds both images and folders"):
        build(fabric_config(root))
    with pytest.raises(DatasetError, match=r"unknown fabric\(s\) \['Velvet'\]"):
        build(fabric_config(layouts.build_fabricvst(tmp_path / "folders"), fabrics=["Velvet"]))


def test_fabricvst_attribute_csv_must_cover_every_fabric(tmp_path):
    root = layouts.build_fabricvst(tmp_path)
    partial = layouts.write_text(root / "partial.csv", "fabric,soft,rough,shinny\nMaterial_1,1,0,0\n")
    with pytest.raises(DatasetError, match=f"{partial} has no row for fabric"):
        build(fabric_config(root, attribute_csvs=["annotator_0.csv", "partial.csv"]))
    other = layouts.write_text(root / "other.csv", "fabric,soft\nMaterial_1,1\nMaterial_10,0\nMaterial_2,2\n")
    with pytest.raises(DatasetError, match=f"{other} line 4: expected a fabric name and 1 values 0/1"):
        build(fabric_config(root, attribute_csvs=["other.csv"]))


# ============================================================================================
# Image folder
# ============================================================================================
def test_image_folder_class_folders(tmp_path):
    root = layouts.build_image_folder(tmp_path) / "classes"
    dataset = build({"name": "image_folder", "root": str(root), "image_size": SIZE, "sensor": "digit"})
    assert dataset.class_names == ["rough", "smooth"]
    assert [record.id for record in dataset.records] == ["rough/img0.png", "rough/nested/img1.png", "smooth/img2.png"]
    assert [record.label for record in dataset.records] == [0, 0, 1] and numbers_of(dataset) == [0, 1, 2]
    assert dataset[0]["sensor"] == "digit"
    fixed = build({"name": "image_folder", "root": str(root), "class_names": ["smooth", "rough", "wet"]})
    assert [record.label for record in fixed.records] == [1, 1, 0] and fixed.num_classes == 3
    with pytest.raises(DatasetError, match=r"sub-folder\(s\) \['rough'\] .* not in class_names"):
        build({"name": "image_folder", "root": str(root), "class_names": ["smooth"]})
    stray = layouts.write_sample(root / "stray.png", 0, "tactile")
    with pytest.raises(DatasetError, match=f"image {stray} is not inside a class sub-folder"):
        build({"name": "image_folder", "root": str(root)})
    assert len(build_lenient({"name": "image_folder", "root": str(root)})[0]) == 3


@pytest.mark.parametrize(
    "labels, class_names, expected_names, expected_labels",
    [
        (["b", "a", "", "b"], [], ["a", "b"], [1, 0, -1, 1]),
        (["2", "0", "-1", "1"], [], ["0", "1", "2"], [2, 0, -1, 1]),
        (["z", "1", "", "x"], ["x", "y", "z"], ["x", "y", "z"], [2, 1, -1, 0]),
    ],
)
def test_image_folder_csv_labels_and_visual_pairs(labels, class_names, expected_names, expected_labels, tmp_path):
    root = layouts.build_image_folder(tmp_path)
    layouts.write_image_folder_csv(root, labels)
    dataset = build(
        {
            "name": "image_folder",
            "root": str(root),
            "csv": "listed/list.csv",
            "image_size": SIZE,
            "class_names": class_names,
        }
    )
    assert dataset.class_names == expected_names and [record.label for record in dataset.records] == expected_labels
    for index, number in enumerate(range(3, 7)):
        check_pair(dataset[index], number)
        assert dataset[index]["id"] == f"touch/{number}.png"


def test_image_folder_csv_problems(tmp_path):
    root = layouts.build_image_folder(tmp_path)
    config = {"name": "image_folder", "root": str(root), "csv": "listed/list.csv"}
    csv_path = layouts.write_image_folder_csv(root, ["1", "0", "1", "0"], visual=False)
    without_visual = build(config)
    assert not without_visual.has_visual and "visual" not in without_visual[0]
    layouts.write_image_folder_csv(root, ["cat", "0", "cat", "dog"])
    with pytest.raises(DatasetError, match="mixes integers and class names"):
        build(config)
    layouts.write_image_folder_csv(root, ["x", "5", "y", "x"])
    with pytest.raises(DatasetError, match=f"{csv_path} line 3: label '5' is not a valid class"):
        build({**config, "class_names": ["x", "y"]})
    (root / "listed" / "vision" / "6.png").unlink()
    dataset, message = build_lenient({**config, "class_names": ["x", "y"]})
    assert len(dataset) == 2 and "skipped 2 bad sample" in message and "missing visual image" in message
    csv_path.write_text("file,label\ntouch/3.png,0\n")
    with pytest.raises(DatasetError, match="include path and label"):
        build(config)
    csv_path.write_text("path,label,label\ntouch/3.png,0,0\n")
    with pytest.raises(DatasetError, match="name each column once"):
        build(config)
    # Extra columns are ignored and a text column becomes the sample's text.
    csv_path.write_text("path,label,note,text\ntouch/3.png,0,anything,a soft cat\n")
    assert build({**config, "class_names": ["x"]})[0]["text"] == "a soft cat"


# ============================================================================================
# Split groups: what each layout says belongs to one recording
# ============================================================================================
def test_each_reader_groups_samples_by_what_its_layout_records(tmp_path):
    def groups(case_name: str, **extra):
        case = next(case for case in CASES if case.name == case_name)
        root = case.build(tmp_path / case_name)
        dataset = build(case.config(root, **extra))
        return dataset.split_unit, dataset.split_groups()

    tag_numbers = [number for number, label in layouts.TAG_LISTS["train"] if label != -1]
    assert groups("touch_and_go") == ("recording", [layouts.TAG_RECORDINGS[n % 2] for n in tag_numbers])
    # Every VisGel fixture line names the same no-contact frame: one recording.
    assert groups("visgel") == ("recording", [layouts.visgel_frame(0, "tactile")] * len(layouts.VISGEL_NUMBERS))
    # Trajectory folders <idx>-<ts> of the runs; the same folder name in two runs is two trajectories.
    assert groups("tvl_hct") == ("trajectory", ["data1/3-1700000003", "data1/4-1700000004", "data2/4-1700000004"])
    assert groups("tvl_ssvtp") == ("sample", None)
    assert groups("objectfolder_real") == ("trial", [f"{obj}/{trial}" for obj, trial, _, _ in layouts.of_real_frames()])
    assert groups("objectfolder_cross") == ("sample", None)
    assert groups("fabricvst") == (
        "fabric",
        [fabric for fabric, numbers in layouts.fabric_numbers().items() for _ in numbers],
    )
    unit, folder_groups = groups("image_folder")
    # rough/img0.png and smooth/img2.png sit in their class folders: each its own group.
    assert unit == "folder" and folder_groups[1] == "rough/nested" and len(set(folder_groups)) == 3


def test_fabricvst_flat_layout_groups_by_fabric(tmp_path):
    root = layouts.build_fabricvst(tmp_path, flat=True)
    dataset = build({"name": "fabricvst", "root": str(root), "image_size": SIZE})
    assert dataset.split_groups() == [fabric for fabric, numbers in layouts.fabric_numbers().items() for _ in numbers]


def test_image_folder_groups_come_from_the_group_column(tmp_path):
    root = layouts.build_image_folder(tmp_path)
    config = {"name": "image_folder", "root": str(root), "csv": "listed/list.csv", "image_size": SIZE}
    csv_path = layouts.write_image_folder_csv(root, ["0", "0", "1", "1"])
    assert build(config).split_groups() is None and build(config).split_unit == "sample"
    csv_path.write_text(
        "path,group,label\ntouch/3.png,rec_a,0\ntouch/4.png,rec_b,0\ntouch/5.png,rec_a,1\ntouch/6.png,,1\n"
    )
    dataset = build(config)
    assert dataset.split_unit == "group"
    assert dataset.split_groups()[:3] == ["rec_a", "rec_b", "rec_a"]
    assert dataset.split_groups()[3] not in {"rec_a", "rec_b"}  # an empty cell: a group of its own


def test_a_split_of_a_reader_keeps_its_groups_on_one_side(tmp_path):
    from vqtouch.plugins.utils.splits import split_dataset

    root = layouts.build_objectfolder_real(tmp_path)
    dataset = build({"name": "objectfolder_real", "root": str(root), "image_size": SIZE})
    for seed in range(5):
        train, held_out = split_dataset(dataset, 0.3, seed)
        assert held_out.split_unit == "trial" and len(held_out) > 0
        assert not set(train.split_groups()) & set(held_out.split_groups())

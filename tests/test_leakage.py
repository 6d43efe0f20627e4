"""Splits without leakage (whole recordings held out) and the near-duplicate check ``vqtouch data leakage``.

Datasets here are tiny and seeded: in-memory ones with chosen groups for the split, and a
video-like image folder (recordings whose frames differ by a few grey levels) for the command.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from vqtouch.core import ConfigError, PluginError, TactileDataset
from vqtouch.plugins.cli.app import main
from vqtouch.plugins.utils.splits import DatasetSubset, split_dataset
from vqtouch.plugins.data import leakage
from vqtouch.plugins.data.leakage import Thumbnails, check_leakage


class TinyDataset(TactileDataset):
    """``len(groups)`` samples whose split groups are ``groups`` (None: no groups); image i is flat grey i/255."""

    split_unit = "recording"

    def __init__(self, groups: list[str] | None, size: int | None = None) -> None:
        self.groups = groups
        self.size = len(groups) if groups is not None else size

    def __len__(self) -> int:
        return self.size

    def __getitem__(self, index: int) -> dict:
        return {
            "tactile": torch.full((3, 8, 8), index / 255),
            "label": -1,
            "text": "",
            "sensor": "test",
            "id": f"s{index}",
        }

    def split_groups(self) -> list[str] | None:
        return self.groups


def uneven_groups(seed: int, count: int = 12) -> list[str]:
    """``count`` recordings of 1 to 9 frames each, listed interleaved (not recording by recording)."""
    generator = torch.Generator().manual_seed(seed)
    sizes = torch.randint(1, 10, (count,), generator=generator).tolist()
    keys = [f"rec{recording}" for recording, size in enumerate(sizes) for _ in range(size)]
    return [keys[i] for i in torch.randperm(len(keys), generator=generator).tolist()]


def groups_of(subset: DatasetSubset) -> set[str]:
    return set(subset.split_groups())


# --------------------------------------------------------------------------------------------
# split_dataset
# --------------------------------------------------------------------------------------------
# Held-out indices of the frame split as it was before split groups existed (computed with that
# implementation): datasets without groups must keep exactly these splits.
FRAME_SPLITS = {
    (20, 0.25, 0): [4, 12, 14, 15, 19],
    (20, 0.25, 1): [0, 1, 2, 3, 16],
    (7, 0.1, 3): [2],
    (50, 0.1, 0): [0, 3, 24, 27, 33],
}


@pytest.mark.parametrize(("size", "fraction", "seed"), list(FRAME_SPLITS))
def test_split_without_groups_is_the_frame_split_it_always_was(size, fraction, seed):
    train, held_out = split_dataset(TinyDataset(None, size), fraction, seed)
    assert held_out.indices == FRAME_SPLITS[size, fraction, seed]
    assert train.indices == sorted(set(range(size)) - set(held_out.indices))
    assert held_out.split_unit == train.split_unit == "sample"
    assert held_out.split_groups() is None


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("fraction", [0.05, 0.1, 0.3, 0.5])
def test_no_group_is_on_both_sides_and_the_share_is_within_one_group(seed, fraction):
    groups = uneven_groups(seed)
    train, held_out = split_dataset(TinyDataset(groups), fraction, seed)
    assert sorted(train.indices + held_out.indices) == list(range(len(groups)))
    assert not groups_of(train) & groups_of(held_out)
    assert held_out.indices and train.indices  # at least one group held out, at least one sample trained on
    largest = max(groups.count(key) for key in set(groups))
    assert abs(len(held_out) - fraction * len(groups)) <= largest
    assert held_out.split_unit == train.split_unit == "recording"


def test_group_split_is_deterministic_seed_dependent_and_independent_of_listing_order():
    groups = uneven_groups(0)
    first = split_dataset(TinyDataset(groups), 0.3, seed=4)[1]
    assert split_dataset(TinyDataset(groups), 0.3, seed=4)[1].indices == first.indices
    held_out_by_seed = {tuple(sorted(groups_of(split_dataset(TinyDataset(groups), 0.3, seed)[1]))) for seed in range(8)}
    assert len(held_out_by_seed) > 1
    # The same recordings listed in another order: the same recordings are held out.
    order = torch.randperm(len(groups), generator=torch.Generator().manual_seed(1)).tolist()
    reordered = split_dataset(TinyDataset([groups[i] for i in order]), 0.3, seed=4)[1]
    assert groups_of(reordered) == groups_of(first)


def test_group_split_holds_out_nothing_at_fraction_zero():
    train, held_out = split_dataset(TinyDataset(uneven_groups(2)), 0.0, seed=0)
    assert len(held_out) == 0 and len(train) == len(uneven_groups(2))


def test_a_single_group_cannot_be_split_and_says_what_to_change():
    with pytest.raises(ConfigError) as info:
        split_dataset(TinyDataset(["only"] * 5), 0.1, seed=0)
    message = str(info.value)
    assert "\n" not in message and "all one recording" in message and "set data.val_fraction=0" in message


def test_subset_groups_are_the_parents_at_its_indices():
    groups = [f"g{i % 3}" for i in range(9)]
    subset = DatasetSubset(TinyDataset(groups), [5, 1, 8])
    assert subset.split_groups() == ["g2", "g1", "g2"] and subset.split_unit == "recording"
    assert DatasetSubset(subset, [2, 0]).split_groups() == ["g2", "g2"]
    # A split of a subset keeps its groups together too.
    train, held_out = split_dataset(DatasetSubset(TinyDataset(groups), list(range(9))), 0.3, seed=0)
    assert not groups_of(train) & groups_of(held_out)


def test_groups_of_the_wrong_length_are_a_plugin_error():
    dataset = TinyDataset(["a", "b"])
    dataset.size = 3
    with pytest.raises(PluginError, match="returned 2 keys for 3 samples"):
        split_dataset(dataset, 0.5, seed=0)


def test_the_generators_code_dataset_splits_as_its_source_dataset():
    """The generator splits its cached codes: the same recordings must be held out as for the tokenizer."""
    from vqtouch.plugins.generator.training import CodesDataset

    source = TinyDataset(uneven_groups(5))
    codes = CodesDataset.collect(torch.zeros(len(source), 2, 2, dtype=torch.long), source, ["label"])
    for fraction in (0.2, 0.4):
        (train_codes, held_out_codes), (train, held_out) = (
            split_dataset(codes, fraction, 1),
            split_dataset(source, fraction, 1),
        )
        assert (held_out_codes.indices, train_codes.indices) == (held_out.indices, train.indices)
        assert held_out_codes.split_unit == "recording"
        assert not groups_of(train_codes) & groups_of(held_out_codes)


def test_procedural_samples_are_each_their_own_group(host):
    dataset = host.build(
        "dataset",
        {"name": "procedural", "num_samples": 20, "image_size": 16},
        sensor=host.build("sensor_family", "gelsight"),
    )
    assert dataset.split_groups() is None
    assert split_dataset(dataset, 0.25, 0)[1].indices == FRAME_SPLITS[20, 0.25, 0]


# --------------------------------------------------------------------------------------------
# The check
# --------------------------------------------------------------------------------------------
def thumbnails(images_BP: torch.Tensor, prefix: str, size: int = 8) -> Thumbnails:
    return Thumbnails(images_BP, [f"{prefix}{i}" for i in range(len(images_BP))], (size, size), size)


def random_images(count: int, seed: int, size: int = 8) -> torch.Tensor:
    return torch.rand(count, 3 * size * size, generator=torch.Generator().manual_seed(seed))


def test_check_finds_a_planted_near_duplicate_and_nothing_in_disjoint_data():
    train = random_images(30, seed=0)
    test = random_images(6, seed=1)
    noise = torch.randn(train.shape[1], generator=torch.Generator().manual_seed(2)) * 0.1 / 255
    test[4] = (train[17] + noise).clamp(0, 1)  # a training image copied into the test set, slightly noisy
    report = check_leakage(thumbnails(train, "train"), thumbnails(test, "test"))
    assert report.near_duplicate_count == 1 and report.summary().startswith("1 of 6 test images")
    (test_index, train_index, distance), *rest = report.closest()
    assert (report.test_ids[test_index], report.train_ids[train_index]) == ("test4", "train17")
    assert distance < 0.25 < rest[0][2]
    disjoint = check_leakage(thumbnails(train, "train"), thumbnails(random_images(6, seed=1), "test"))
    assert disjoint.near_duplicate_count == 0 and disjoint.near_duplicate_fraction == 0.0
    assert float(disjoint.distance_M.min()) > 50  # independent uniform noise: about 85 levels apart


def test_distances_are_mean_absolute_differences_in_8_bit_levels_whatever_the_chunking(monkeypatch):
    train, test = random_images(40, seed=3), random_images(25, seed=4)
    expected = (test[:, None] - train[None]).abs().mean(-1) * 255
    whole = check_leakage(thumbnails(train, "a"), thumbnails(test, "b"))
    monkeypatch.setattr(leakage, "DISTANCE_CHUNK_ELEMENTS", 3 * 40)  # 3 test rows per chunk
    chunked = check_leakage(thumbnails(train, "a"), thumbnails(test, "b"))
    for report in (whole, chunked):
        assert torch.allclose(report.distance_M, expected.min(1).values, atol=1e-3)
        assert torch.equal(report.nearest_M, expected.argmin(1))
    assert whole.to_json()["nearest"] == chunked.to_json()["nearest"]


def test_an_exact_copy_is_a_near_duplicate_at_threshold_zero():
    train = random_images(5, seed=5)
    report = check_leakage(thumbnails(train, "a"), thumbnails(train[2:3].clone(), "b"), threshold=0.0)
    assert report.near_duplicate_count == 1 and report.closest()[0][1] == 2


def test_images_of_different_aspects_are_refused():
    train = Thumbnails(random_images(2, 0), ["a", "b"], (64, 64), 8)
    test = Thumbnails(random_images(2, 1), ["c", "d"], (24, 32), 8)
    with pytest.raises(ConfigError, match="different aspects"):
        check_leakage(train, test)


# --------------------------------------------------------------------------------------------
# The command, end to end
# --------------------------------------------------------------------------------------------
RECORDINGS, FRAMES = 10, 6


def write_recordings(root: Path) -> Path:
    """A video-like image folder: RECORDINGS recordings of FRAMES 16 x 16 frames each.  A recording's
    frames share one random picture and differ in a 2 x 2 patch by 4 grey levels per frame;
    recordings differ everywhere.  ``grouped.csv`` has a group column, ``frames.csv`` does not."""
    from PIL import Image

    generator = torch.Generator().manual_seed(0)
    rows = []
    for recording in range(RECORDINGS):
        picture = torch.randint(0, 200, (16, 16, 3), generator=generator, dtype=torch.uint8)
        for frame in range(FRAMES):
            pixels = picture.clone()
            pixels[7:9, 7:9] += 4 * frame
            path = root / f"rec{recording}" / f"{frame}.png"
            path.parent.mkdir(parents=True, exist_ok=True)
            Image.fromarray(pixels.numpy()).save(path)
            rows.append((f"rec{recording}/{frame}.png", f"rec{recording}"))
    (root / "grouped.csv").write_text("path,label,group\n" + "".join(f"{p},,{g}\n" for p, g in rows))
    (root / "frames.csv").write_text("path,label\n" + "".join(f"{p},\n" for p, _ in rows))
    return root


def folder_spec(root: Path, csv: str, **options) -> str:
    return json.dumps({"name": "image_folder", "root": str(root), "csv": csv, **options})


def test_command_shows_leakage_of_a_frame_split_and_none_of_a_recording_split(tmp_path, capsys):
    root = write_recordings(tmp_path / "video")
    assert (
        main(
            [
                "data",
                "leakage",
                "--dataset",
                folder_spec(root, "frames.csv"),
                "--val-fraction",
                "0.2",
                "--out",
                str(tmp_path / "frames"),
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "split by sample" in out and "12 of 12 test images have a near-duplicate in train (threshold 0.25)" in out
    assert (
        main(
            [
                "data",
                "leakage",
                "--dataset",
                folder_spec(root, "grouped.csv"),
                "--val-fraction",
                "0.2",
                "--out",
                str(tmp_path / "groups"),
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "split by group" in out and "0 of 12 test images have a near-duplicate in train" in out
    record = json.loads((tmp_path / "groups" / "leakage.json").read_text())
    assert record["split"] == {"val_fraction": 0.2, "seed": 0, "unit": "group"}
    assert record["near_duplicates"] == 0 and len(record["nearest"]) == 12
    held_out = {pair["test_id"].split("/")[0] for pair in record["nearest"]}
    trained = {pair["train_id"].split("/")[0] for pair in record["nearest"]}
    assert len(held_out) == 2 and not held_out & trained
    frames = json.loads((tmp_path / "frames" / "leakage.json").read_text())
    # Every flagged pair is two frames of one recording.
    assert all(pair["test_id"].split("/")[0] == pair["train_id"].split("/")[0] for pair in frames["nearest"])
    assert (tmp_path / "frames" / "closest_pairs.png").is_file()


def test_command_compares_two_datasets_and_can_fail_for_ci(tmp_path, capsys):
    root = write_recordings(tmp_path / "video")
    argv = [
        "data",
        "leakage",
        "--train",
        folder_spec(root, "frames.csv"),
        "--test",
        folder_spec(root, "grouped.csv"),
        "--show",
        "3",
    ]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "60 of 60 test images have a near-duplicate in train" in out
    assert len([line for line in out.splitlines() if line.startswith("     0.000*")]) == 3
    assert main([*argv, "--fail-above", "0.5"]) == 1
    assert "above --fail-above 0.5: failing" in capsys.readouterr().out


def test_command_checks_the_procedural_split(capsys):
    assert (
        main(
            [
                "data",
                "leakage",
                "--dataset",
                '{"name": "procedural", "num_samples": 12}',
                "--sensor",
                "gelsight_mini",
                "--show",
                "0",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "split by sample (val_fraction 0.1, seed 0): 11 train, 1 held out" in out
    assert "of 1 test images have a near-duplicate" in out and "closest pairs" not in out


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--dataset", "touch_and_goo"], "--dataset: unknown dataset 'touch_and_goo'"),
        (["--train", "procedural"], "give --dataset SPEC to check the train/held-out split of one dataset, or both"),
        (["--dataset", "procedural", "--train", "procedural", "--test", "procedural"], "not both"),
        (["--dataset", '{"name": "procedural", '], "--dataset is not valid JSON"),
        (["--dataset", "image_folder"], "--dataset: dataset 'image_folder' needs its folder"),
        (["--dataset", "procedural", "--val-fraction", "0"], "--val-fraction 0: give a fraction between 0 and 1"),
        (["--dataset", "procedural", "--threshold", "-1"], "argument --threshold: -1: must be a finite number >= 0"),
        (["--dataset", "procedural", "--show", "-1"], "argument --show: -1: must be an integer >= 0"),
        (["--dataset", "procedural", "--sensor", "gelsite"], "--sensor: unknown sensor_family 'gelsite'"),
        (
            [
                "--train",
                '{"name": "procedural", "num_samples": 2, "image_size": [16, 32]}',
                "--test",
                '{"name": "procedural", "num_samples": 2, "image_size": 16}',
            ],
            "of different aspects",
        ),
    ],
)
def test_bad_input_is_one_line_with_exit_2(capsys, argv, message):
    assert main(["data", "leakage", *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("vqtouch: error: ") and message in err and err.count("\n") == 1


def test_command_has_help(capsys):
    assert main(["data", "leakage", "--help"]) == 0
    assert "--fail-above FRACTION" in capsys.readouterr().out

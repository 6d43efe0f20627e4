"""Native-aspect images: ``image_size`` as (height, width) through configs, image files and
every command, from rendering and training to generation, clustering and adaptation."""

from __future__ import annotations

import argparse
import json

import pytest
import torch
from PIL import Image

import generator_runs
from vqtouch.core import ConfigError, load_plugins, read_metadata, resolve_config
from vqtouch.plugins.cli.app import main
from vqtouch.core.image_size import image_size_argument
from vqtouch.plugins.utils.images import ImageLoader, crop_box, save_png

HOST = load_plugins(autoload=False)
#: Rows x columns of every image in the end-to-end run: the 2:3 aspect, small enough to train in seconds.
SIZE_HW = (32, 48)


def test_image_size_config_takes_a_side_or_height_and_width():
    sizes = [
        resolve_config("reconstruction", overrides=[f"data.image_size={value}"], host=HOST).data.image_size
        for value in ("64", "[240, 320]", "[64, 64]")
    ]
    assert sizes == [64, (240, 320), 64]  # a square pair reads as its side: one spelling per size
    with pytest.raises(ConfigError, match=r"data.image_size: expected a side S .* \(got \[240, 320, 3\]\)"):
        resolve_config("reconstruction", overrides=["data.image_size=[240, 320, 3]"], host=HOST)


def test_image_size_argument_reads_a_side_or_height_x_width():
    assert [image_size_argument(text) for text in ("64", "240x320", "48X48", "240,320")] == [
        64,
        (240, 320),
        48,
        (240, 320),
    ]
    for bad in ("", "x", "240x", "4x320", "1x2x3", "big"):
        with pytest.raises(argparse.ArgumentTypeError, match="expected a side S"):
            image_size_argument(bad)


@pytest.mark.parametrize(
    "width, height, aspect_hw, box",
    [
        (400, 200, (1, 1), (100.0, 0.0, 300.0, 200.0)),  # a square from a wide image: its middle
        (400, 200, (1, 2), (0.0, 0.0, 400.0, 200.0)),  # the image's own aspect: all of it
        (400, 200, (3, 4), (66.66666666666667, 0.0, 333.33333333333337, 200.0)),  # 3:4 inside 1:2
        (200, 400, (3, 4), (0.0, 125.0, 200.0, 275.0)),  # 3:4 inside a tall image: a band across the middle
    ],
)
def test_crop_box_is_the_largest_centred_box_of_the_aspect(width, height, aspect_hw, box):
    left, top, right, bottom = crop_box(width, height, "center", aspect_hw)
    assert (left, top, right, bottom) == pytest.approx(box)
    assert (bottom - top) * aspect_hw[1] == pytest.approx((right - left) * aspect_hw[0])


def test_image_loader_crops_to_the_requested_aspect(tmp_path):
    # A 1:2 image: red outer quarters, green middle half.  A square crop sees only green; 1:2 sees all.
    image = torch.zeros(3, 100, 200)
    image[0, :, :50] = image[0, :, 150:] = 1
    image[1, :, 50:150] = 1
    path = save_png(image, tmp_path / "wide.png")
    square = ImageLoader(size=20).load(path)
    # Bicubic resampling reads a pixel past the box: the outermost columns see a trace of red.
    assert square.shape == (3, 20, 20) and float(square[0, :, 1:-1].max()) < 0.01
    assert float(square[1, :, 1:-1].min()) > 0.99
    whole = ImageLoader(size=(20, 40)).load(path)
    assert whole.shape == (3, 20, 40)
    assert float(whole[0, :, :8].min()) > 0.95 and float(whole[1, :, 12:28].min()) > 0.95


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A tiny label-to-touch run at 32 x 48: tokenizer then generator."""
    out = tmp_path_factory.mktemp("aspect") / "run"
    assert main(generator_runs.train_args(out, f"data.image_size={list(SIZE_HW)}")) == 0
    return out


def _png_hw(path):
    with Image.open(path) as image:
        return image.height, image.width


def test_training_and_generation_keep_the_aspect(run, tmp_path):
    header = read_metadata(run / "checkpoints" / "generator" / "step-00000006" / "generator.safetensors")
    context = json.loads(header["vqtouch.context"])
    assert context["image_size"] == list(SIZE_HW) and context["code_grid"] == [16, 24]  # f = 2
    assert json.loads((run / "eval.json").read_text())["val_samples"] == 6
    out = tmp_path / "generated"
    assert (
        main(
            [
                "generate",
                "--run",
                str(run),
                "--label",
                "0",
                "--label",
                "2",
                "--n",
                "2",
                "--steps",
                "3",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    assert [_png_hw(out / f"sample_{i:04d}.png") for i in range(2)] == [SIZE_HW, SIZE_HW]


def test_reconstruct_crops_other_images_to_the_tokenizer_aspect(run, tmp_path):
    folder = tmp_path / "frames" / "press"
    folder.mkdir(parents=True)
    for index in range(3):  # 3:4 frames (a GelSight's 240 x 320, scaled down), not the tokenizer's 2:3
        save_png(torch.rand(3, 60, 80, generator=torch.Generator().manual_seed(index)), folder / f"{index}.png")
    out = tmp_path / "reconstructed"
    assert main(["reconstruct", "--run", str(run), "--images", str(folder.parent), "--out", str(out)]) == 0
    record = json.loads((out / "reconstruct.json").read_text())
    assert record["images"] == 3 and record["image_size"] == list(SIZE_HW)
    # Originals above reconstructions, 3 columns, 2 px padding: every image 32 x 48.
    assert _png_hw(out / "reconstructions.png") == (2 * (32 + 2) + 2, 3 * (48 + 2) + 2)


def test_cluster_and_adapt_work_at_the_aspect(run, tmp_path):
    families = tmp_path / "families"
    assert (
        main(
            [
                "cluster",
                "--run",
                str(run),
                "--images",
                "8",
                "--families",
                "2",
                "--out",
                str(families),
                "--sensors",
                "gelsight",
                json.dumps({"name": "gelsight", "variant": {"seed": 1}}),
                "digit",
                json.dumps({"name": "digit", "variant": {"seed": 2}}),
            ]
        )
        == 0
    )
    assert json.loads((families / "cluster.json").read_text())["image_size"] == list(SIZE_HW)
    adapted = tmp_path / "adapted"
    assert (
        main(
            [
                "adapt",
                "--run",
                str(run),
                "--families",
                str(families),
                "--images",
                json.dumps({"name": "gelsight", "variant": {"seed": 7, "noise_std": 0.01}}),
                "--out",
                str(adapted),
                "--shots",
                "4",
                "--ratio",
                "2",
                "--steps",
                "2",
                "--eval-images",
                "4",
                "--batch-size",
                "4",
                "--threshold",
                "1",
            ]
        )
        == 0
    )
    context = json.loads(read_metadata(adapted / "autoencoder.safetensors")["vqtouch.context"])
    assert context["image_size"] == list(SIZE_HW)


def test_render_command_writes_native_aspect_scenes(tmp_path):
    out = tmp_path / "render"
    assert (
        main(
            [
                "--no-progress",
                "data",
                "render",
                "--n",
                "2",
                "--image-size",
                "32x48",
                "--out",
                str(out),
                "--sensor",
                '{"name": "gelsight", "view": "full"}',
            ]
        )
        == 0
    )
    pictures = sorted(path for path in out.rglob("*.png") if path.name != "preview.png")
    assert len(pictures) == 4 and {_png_hw(path) for path in pictures} == {SIZE_HW}  # 2 tactile, 2 visual


def test_native_view_renders_round_contacts_and_the_default_view_stretches_them():
    """GelSight's full 3:4 frame at 240 x 320 has square pixels, so a round press stays round; the
    default square view resampled to 3:4 has non-square pixels, and says so by its extent."""
    full = HOST.build("sensor_family", {"name": "gelsight", "view": "full"})
    rows_mm, cols_mm = full.imaged_extent_mm(240, 320)
    assert rows_mm / 240 == pytest.approx(cols_mm / 320)
    square = HOST.build("sensor_family", "gelsight")
    rows_mm, cols_mm = square.imaged_extent_mm(240, 320)
    assert rows_mm == pytest.approx(cols_mm)  # the same square area on 240 rows and 320 columns
    dataset = HOST.build("dataset", {"name": "procedural", "num_samples": 1, "image_size": [24, 32]}, sensor=full)
    sample = dataset[0]
    assert sample["tactile"].shape == sample["visual"].shape == (3, 24, 32)


def test_pixel_centres_are_the_centred_mm_grid_of_each_axis():
    from vqtouch.core.image_size import pixel_centres_mm

    ys, xs = pixel_centres_mm(3, 4, (6.0, 2.0))
    assert ys[:, 0].tolist() == [-2.0, 0.0, 2.0] and xs[0].tolist() == [-0.75, -0.25, 0.25, 0.75]
    assert (ys == ys[:, :1]).all() and (xs == xs[:1]).all()  # rows vary down, columns across


def test_a_sphere_stays_round_on_a_non_square_image_with_square_pixels():
    """96 x 128 pixels over 15 x 20 mm (GelSight's 3:4 view): a pressed sphere covers as many rows as
    columns (over the square 15 mm it would cover a third more columns)."""
    from vqtouch.sensors.objects import CLASS_NAMES, OBJECT_CLASSES, sample_contact

    sphere = CLASS_NAMES.index("sphere")
    contact = sample_contact(
        OBJECT_CLASSES[sphere],
        sphere,
        torch.Generator().manual_seed(0),
        (96, 128),
        (15.0, 20.0),
        depth_range_mm=(1.0, 1.0),
    )
    touched = contact.indentation_mm_HW > 0
    rows, cols = int(touched.any(1).sum()), int(touched.any(0).sum())
    assert rows > 15 and abs(rows - cols) <= 1

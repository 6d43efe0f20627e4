"""The contact region (plugins/evaluation/contact.py): the floor on noise-free images, the noise
bar under DIGIT's published camera noise, and a press recovered through that noise."""

import math

import pytest
import torch

from vqtouch.plugins.evaluation.contact import CONTACT_THRESHOLD, NOISE_FACTOR, contact_mask

NOISE = 7 / 255  # DIGIT's published camera noise (tacto's config_digit.yml)


def _press(size=64):
    background = torch.full((4, 3, size, size), 0.5)
    images = background.clone()
    images[:, :, 10:30, 20:40] += 0.3  # a press covering 400 of 4096 pixels
    return images, background


def test_noise_free_images_use_the_floor_exactly():
    images, background = _press()
    images[:, :, 40:44, :] += CONTACT_THRESHOLD * 1.5  # just above the floor
    images[:, :, 50:54, :] += CONTACT_THRESHOLD * 0.5  # just below
    mask = contact_mask(images, background)
    expected = torch.zeros(4, 64, 64, dtype=torch.bool)
    expected[:, 10:30, 20:40] = True
    expected[:, 40:44, :] = True
    assert torch.equal(mask, expected)


def test_camera_noise_alone_is_not_contact_and_a_press_shows_through_it():
    generator = torch.Generator().manual_seed(0)
    images, background = _press()
    noisy = images + NOISE * torch.randn(images.shape, generator=generator)
    noisy_background = background + NOISE * torch.randn(background.shape, generator=generator)
    flat = background + NOISE * torch.randn(background.shape, generator=generator)
    # Without the noise bar, 7/255 noise on both sides puts most pixels above the 0.02 floor.
    assert float(((flat - noisy_background).abs().mean(dim=1) > CONTACT_THRESHOLD).double().mean()) > 0.5
    assert float(contact_mask(flat, noisy_background).double().mean()) < 1e-3
    mask = contact_mask(noisy, noisy_background)
    truth = torch.zeros_like(mask)
    truth[:, 10:30, 20:40] = True
    assert float((mask & truth).sum() / (mask | truth).sum()) > 0.98  # intersection over union
    assert NOISE_FACTOR * NOISE * 2**0.5 < 0.3  # the press is well above the bar it sets


# -- the background of a dataset (dataset_background) --------------------------------------------

from vqtouch.core import BuildContext, TactileDataset, load_plugins  # noqa: E402
from vqtouch.plugins.utils.splits import split_dataset  # noqa: E402
from vqtouch.plugins.evaluation.contact import RENDERED_BACKGROUND, dataset_background, evenly_spaced  # noqa: E402

HOST = load_plugins(autoload=False)
SIZE = 32
BLOB = 6  # the side of each frame's square press, in pixels


def _known_background(size=SIZE):
    """(3, H, W) a smooth, channel-dependent background on the 8-bit grid (so a PNG holds it exactly)."""
    rows = torch.arange(size).view(size, 1)
    columns = torch.arange(size).view(1, size)
    levels = torch.stack([60 + 2 * rows + columns, 90 + rows + 2 * columns, 120 + rows - columns + size])
    return levels.to(torch.uint8).float() / 255


def _frames(count, size=SIZE):
    """``count`` captured frames: the known background plus one press per frame, each at its own
    place (no pixel is pressed in two frames), and the press masks (count, H, W)."""
    background = _known_background(size)
    frames, masks = [], []
    per_row = size // BLOB
    for index in range(count):
        top, left = (index // per_row) * BLOB, (index % per_row) * BLOB
        mask = torch.zeros(size, size, dtype=torch.bool)
        mask[top : top + BLOB, left : left + BLOB] = True
        frames.append(torch.where(mask, (background + 64 / 255).clamp(max=1), background))
        masks.append(mask)
    return torch.stack(frames), torch.stack(masks), background


class CapturedFrames(TactileDataset):
    """Frames held in memory, as a reader of captured images gives them (no rendering sensor); it
    records which samples were read."""

    def __init__(self, frames):
        self.frames = frames
        self.read: list[int] = []

    def __len__(self):
        return len(self.frames)

    def __getitem__(self, index):
        self.read.append(index)
        return {"tactile": self.frames[index], "label": -1, "text": "", "sensor": "captured", "id": str(index)}


def test_a_rendered_datasets_background_is_its_sensors_no_contact_render_exactly():
    sensor = HOST.build("sensor_family", {"name": "digit"})  # camera noise: the render depends on the seed
    dataset = HOST.build(
        "dataset",
        {"name": "procedural", "num_samples": 12, "image_size": SIZE, "seed": 0},
        BuildContext(image_size=SIZE),
        sensor=sensor,
    )
    assert dataset.rendering_sensor() is sensor
    expected = sensor.render(torch.zeros(1, SIZE, SIZE), generator=torch.Generator().manual_seed(0))[0]
    train, _ = split_dataset(dataset, 0.25, seed=0)
    for given in (dataset, train):  # a split forwards its dataset's rendering sensor
        background, source = dataset_background(given, (SIZE, SIZE))
        assert torch.equal(background, expected) and source == RENDERED_BACKGROUND
    # The images' median is not it: the render is the exact background, not an estimate from the images.
    rendered = torch.stack([dataset[i]["tactile"] for i in range(len(dataset))])
    assert not torch.equal(rendered.median(dim=0).values, expected)


def test_captured_frames_get_the_per_pixel_median_which_recovers_the_background_and_the_presses():
    frames, masks, known = _frames(10)
    dataset = CapturedFrames(frames)
    assert dataset.rendering_sensor() is None
    background, source = dataset_background(dataset, (SIZE, SIZE))
    # Each pixel is pressed in at most one of the 10 frames: its median is the background's value.
    assert torch.equal(background, known)
    assert source.startswith("the per-pixel median of 10 of 10 training images")
    for index in (0, 4, 9):
        mask = contact_mask(frames[index : index + 1], background[None])[0]
        assert torch.equal(mask, masks[index])  # the frame's press and nothing else
    # At most max_images samples, evenly spaced from the first to the last, are read.
    dataset.read.clear()
    estimate, source = dataset_background(dataset, (SIZE, SIZE), max_images=4)
    assert dataset.read == evenly_spaced(10, 4) == [0, 3, 6, 9]
    assert torch.equal(estimate, known) and source.startswith("the per-pixel median of 4 of 10 ")


def test_too_few_captured_frames_have_no_background_and_say_why():
    frames, _, _ = _frames(1)
    background, reason = dataset_background(CapturedFrames(frames), (SIZE, SIZE))
    assert background is None and reason.startswith("none: ") and "at least 2" in reason


def test_the_tokenizer_stage_scores_captured_frames_without_a_sensor_beside_their_median_background(tmp_path):
    """A folder of real frames and no ``sensor``: the stage still scores the background and the
    contact region, against the training frames' median (not a rendered sensor's background, which
    would put the whole image in contact)."""
    import json

    from PIL import Image

    from generator_runs import TINY_TOKENIZER
    from vqtouch.core import Assembly, resolve_config
    from vqtouch.plugins.runtime.execution import run_stage
    from vqtouch.plugins.runtime.run_dir import RunDir

    frames, _, _ = _frames(16)
    for index, frame in enumerate(frames):
        path = tmp_path / "frames" / ("a" if index % 2 else "b") / f"{index:02d}.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray((frame * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()).save(path)
    overrides = [item for item in TINY_TOKENIZER if not item.startswith("data.dataset")]
    config = resolve_config(
        "reconstruction",
        host=HOST,
        overrides=[
            *overrides,
            "sensor=null",
            'stages=["tokenizer"]',
            'metrics=[{"name": "psnr"}]',
            "data.val_fraction=0.25",
            json.dumps({"name": "image_folder", "root": str(tmp_path / "frames")}).join(["data.dataset=", ""]),
        ],
    )
    run = RunDir.create(config, host=HOST, path=tmp_path / "run")
    outcome = run_stage("tokenizer", Assembly(config, HOST), run)
    assert outcome.status == "ran", outcome.describe()
    scores = json.loads((run.path / "eval.json").read_text())
    assert scores["background"].startswith("the per-pixel median of ")
    for key in ("psnr", "background_psnr", "contact_psnr", "background_contact_psnr"):
        assert isinstance(scores[key], float), key
    # Closed form: the background is the frames' own (the median recovers it exactly, through the
    # PNGs' 8-bit grid), so every held-out frame differs from it by 64/255 on its press (36 of 1024
    # pixels) alone, and that press is the contact region.
    press, share = 64 / 255, BLOB * BLOB / SIZE**2
    assert scores["contact_fraction"] == round(share, 4)
    assert scores["background_psnr"] == pytest.approx(-10 * math.log10(share * press**2), abs=1e-3)
    assert scores["background_contact_psnr"] == pytest.approx(-10 * math.log10(press**2), abs=1e-3)
    # A separate dataset scored whole (`evaluate reconstruction --dataset`) is scored against its own
    # background: here the frames of a sensor 20/255 darker everywhere, whose whole image would be
    # "contact" against the run's training background.
    from vqtouch.plugins.cli.app import main

    darker = tmp_path / "darker"
    for index, frame in enumerate(frames):
        path = darker / ("a" if index % 2 else "b") / f"{index:02d}.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        shifted = (frame * 255).round() - 20
        Image.fromarray(shifted.to(torch.uint8).permute(1, 2, 0).numpy()).save(path)
    spec = json.dumps({"name": "image_folder", "root": str(darker)})
    assert main(["--no-progress", "evaluate", "reconstruction", "--run", str(run.path), "--dataset", spec]) == 0
    evaluated = json.loads(next(run.path.glob("evaluation_*_dataset.json")).read_text())
    assert evaluated["background"].startswith("the per-pixel median of 16 of 16 evaluated images")
    assert evaluated["contact_fraction"] == round(share, 4)
    assert evaluated["background_contact_psnr"] == pytest.approx(-10 * math.log10(press**2), abs=1e-3)

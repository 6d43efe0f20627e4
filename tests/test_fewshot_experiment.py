"""`vqtouch evaluate fewshot` (Table 4) at toy size: what each arm's trainer received, the zero-shot
row and the no-contact background against independent recomputations, the folder target's limits
and background, the refusals, and the files the command writes."""

import json
import statistics

import pytest
import torch

from vqtouch.core import ConfigError, load_plugins, read_metadata
from vqtouch.plugins.cli.app import main
from vqtouch.plugins.utils.images import save_png
from vqtouch.plugins.adaptation.adapt_images import family_images, target_images
from vqtouch.plugins.adaptation.families import load_families, sensor_images
from vqtouch.plugins.adaptation.fewshot import BACKGROUND, SCRATCH, SHOTS_ALONE, ZERO_SHOT, evaluate_fewshot
from vqtouch.plugins.scenes import GELSIGHT_DERIVATIVE_II

HOST = load_plugins(autoload=False)
TARGET = json.dumps(GELSIGHT_DERIVATIVE_II)


def _metric(name, predicted, truth):
    metric = HOST.build("metric", {"name": name})
    metric.update(predicted, truth)
    return float(metric.compute())


def _frames(folder, images):
    folder.mkdir()
    for index, image in enumerate(images):
        save_png(image, folder / f"frame_{index:02d}.png")
    return folder


def test_every_arm_trains_on_its_own_images_and_scores_the_same_held_out_images(
    family_tokenizer_run, family_clusters, tokenizer_trainer_calls, tmp_path
):
    from vqtouch.plugins.evaluation.contact import contact_region_scores, no_contact_image
    from vqtouch.plugins.tokenizer import load_tokenizer, reconstruct_all

    out = tmp_path / "fewshot"
    result = evaluate_fewshot(
        family_tokenizer_run,
        HOST,
        out,
        target=TARGET,
        seeds=[0, 1],
        counts=(8, 4),
        ratio=2.0,
        steps=2,
        scratch_steps=3,
        eval_images=4,
        families=family_clusters,
        report=lambda line: None,
    )
    rows = result["rows"]
    arms = [SCRATCH, ZERO_SHOT, SHOTS_ALONE, "mixed 1:2", BACKGROUND]
    assert sorted((row["n"], row["arm"], row["seed"]) for row in rows) == sorted(
        (n, arm, seed) for n in (4, 8) for arm in arms for seed in (0, 1)
    )

    # Each trainer got exactly its arm's images: the scratch arm and the shots-alone arm the N target
    # images alone, the mixed arm those N followed by ratio x N images of the seed's family.
    families = load_families(family_clusters, HOST)
    expected = []
    for assigned in result["assignments"]:
        seed = assigned["seed"]
        for n in (4, 8):
            _, source, shots, _ = target_images(TARGET, HOST, shots=n, eval_images=4, image_size=32, seed=seed)
            family_N, _ = family_images(
                families, assigned["family"], HOST, count=2 * n, image_size=32, seed=seed, exclude=source
            )
            expected += [("scratch", shots, 3), ("adapt", shots, 2), ("adapt", torch.cat([shots, family_N]), 2)]
    assert len(tokenizer_trainer_calls) == len(expected) == 12
    for stage, images, steps in expected:
        matches = [
            call
            for call in tokenizer_trainer_calls
            if call["stage"] == stage
            and call["steps"] == steps
            and call["images"].shape == images.shape
            and torch.equal(call["images"], images)
        ]
        assert len(matches) == 1, (stage, len(images))
    mixed_sizes = sorted(len(call["images"]) for call in tokenizer_trainer_calls if len(call["images"]) not in (4, 8))
    assert mixed_sizes == [12, 12, 24, 24]  # N (1 + ratio), counted from what the trainers received
    by_key = {(row["n"], row["arm"], row["seed"]): row for row in rows}
    assert by_key[(8, "mixed 1:2", 1)]["train_images"] == 24 and by_key[(8, SCRATCH, 1)]["train_images"] == 8

    tokenizer, _ = load_tokenizer(family_tokenizer_run, HOST)
    sensor = HOST.build("sensor_family", GELSIGHT_DERIVATIVE_II)
    for seed in (0, 1):
        _, _, _, held_out = target_images(TARGET, HOST, shots=4, eval_images=4, image_size=32, seed=seed)
        # Zero-shot: the unchanged family tokenizer on the held-out images, at every N.
        reconstruction = reconstruct_all(tokenizer, held_out)
        for n in (4, 8):
            zero_shot = by_key[(n, ZERO_SHOT, seed)]
            assert zero_shot["ssim"] == pytest.approx(_metric("ssim", reconstruction, held_out), abs=1e-4)
            assert zero_shot["psnr"] == pytest.approx(_metric("psnr", reconstruction, held_out), abs=1e-4)
        # The background row is the sensor's no-contact image scored directly on the same images.
        background = no_contact_image(sensor, held_out)
        contact = contact_region_scores({"": background}, held_out, background[:1])
        for n in (4, 8):
            row = by_key[(n, BACKGROUND, seed)]
            assert row["ssim"] == pytest.approx(_metric("ssim", background, held_out), abs=1e-4)
            assert row["psnr"] == pytest.approx(_metric("psnr", background, held_out), abs=1e-4)
            assert row["contact_psnr"] == pytest.approx(contact["contact_psnr"], abs=1e-4)
            assert row["contact_fraction"] == contact["contact_fraction"] > 0
        # Every arm of the seed carries the same background scores and contact region: one set of held-out images.
        for arm in arms[:-1]:
            for n in (4, 8):
                scored = by_key[(n, arm, seed)]
                assert scored["held_out"] == 4 and "contact_psnr" in scored and "contact_ssim" in scored
                assert scored["background_psnr"] == by_key[(n, BACKGROUND, seed)]["psnr"]
                assert scored["contact_fraction"] == contact["contact_fraction"]

    summary = next(row for row in result["summary"] if row["n"] == 8 and row["arm"] == "mixed 1:2")
    values = [by_key[(8, "mixed 1:2", seed)]["contact_psnr"] for seed in (0, 1)]
    assert summary["seeds"] == 2 and summary["contact_psnr"] == pytest.approx(statistics.fmean(values), abs=1e-5)
    assert summary["contact_psnr_std"] == pytest.approx(statistics.pstdev(values), abs=1e-5)
    header = read_metadata(out / "seed1" / "scratch-8" / "autoencoder.safetensors")
    assert header["fewshot.arm"] == "scratch" and header["fewshot.train_images"] == "8"
    assert json.loads((out / "seed0" / "mixed-4" / "adapt.json").read_text())["family_images"] == 8
    # The zero-shot row's family score is the unchanged tokenizer's on the family's held-out images, as the
    # mixed arm's own adaptation measured it before fine-tuning.
    for seed in (0, 1):
        for n in (4, 8):
            before = json.loads((out / f"seed{seed}" / f"mixed-{n}" / "adapt.json").read_text())["family_held_out"]
            assert by_key[(n, ZERO_SHOT, seed)]["family_psnr"] == before["before"]["psnr"]
            assert by_key[(n, "mixed 1:2", seed)]["family_psnr"] == before["after"]["psnr"]
    markdown = (out / "fewshot.md").read_text()
    assert "| 4 | no-contact background |" in markdown and "- N = 8: mixed 1:2 " in markdown


def test_a_folder_target_too_small_for_n_is_refused_before_anything_trains(
    family_tokenizer_run, family_clusters, tokenizer_trainer_calls, tmp_path, capsys
):
    folder = _frames(tmp_path / "frames", sensor_images("gelsight", HOST, count=8, image_size=32).images)
    out = tmp_path / "fewshot"
    assert (
        main(
            [
                "evaluate",
                "fewshot",
                "--run",
                str(family_tokenizer_run),
                "--out",
                str(out),
                "--target",
                str(folder),
                "--n",
                "4",
                "8",
                "--families",
                str(family_clusters),
            ]
        )
        == 2
    )
    error = capsys.readouterr().err
    assert error.count("\n") == 1
    assert f"vqtouch: error: --n 8: the folder {folder} holds 8 images; the largest usable --n is 7" in error
    assert tokenizer_trainer_calls == [] and not out.exists()
    # The same frames one level down (a class sub-folder, as `vqtouch data render` or a labelled
    # dataset keeps them) are read through the image_folder reader: the same 8 images are counted.
    nested = tmp_path / "nested"
    (nested / "tactile").mkdir(parents=True)
    folder.rename(nested / "tactile" / "frames")
    args = ["evaluate", "fewshot", "--run", str(family_tokenizer_run), "--out", str(out), "--target", str(nested)]
    assert main([*args, "--n", "4", "8", "--families", str(family_clusters)]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and f"the folder {nested} holds 8 images; the largest usable --n is 7" in error
    assert tokenizer_trainer_calls == [] and not out.exists()


def test_a_folder_targets_background_is_the_median_of_its_images(family_tokenizer_run, family_clusters, tmp_path):
    images = sensor_images("gelsight", HOST, count=10, image_size=32, seed=5).images
    folder = _frames(tmp_path / "frames", images)
    result = evaluate_fewshot(
        family_tokenizer_run,
        HOST,
        tmp_path / "fewshot",
        target=str(folder),
        seeds=[0],
        counts=[4],
        ratio=1.0,
        steps=1,
        scratch_steps=1,
        eval_images=64,
        families=family_clusters,
        report=lambda line: None,
    )
    assert result["held_out"] == 6  # the 10 images minus the largest N
    _, _, _, held_out = target_images(str(folder), HOST, shots=4, eval_images=6, image_size=32, seed=0)
    stored = sensor_images(str(folder), HOST, count=10, image_size=32).images  # as the PNGs read back
    median = stored.median(dim=0).values.expand_as(held_out)
    row = next(row for row in result["rows"] if row["arm"] == BACKGROUND)
    assert row["psnr"] == pytest.approx(_metric("psnr", median, held_out), abs=1e-4)
    assert "the per-pixel median of 10 of the folder's 10 images" in (tmp_path / "fewshot" / "fewshot.md").read_text()


@pytest.mark.parametrize(
    "flags, message",
    [
        (["--n", "4", "4"], "--n 4 4 repeats a count"),
        (["--ratio", "0"], "--ratio 0: the mixed arm needs family images"),
        (["--seeds", "1", "1"], "--seeds 1 1 repeats a seed"),
    ],
)
def test_bad_settings_get_one_line_errors(family_tokenizer_run, tmp_path, capsys, flags, message):
    assert main(["evaluate", "fewshot", "--run", str(family_tokenizer_run), "--out", str(tmp_path / "x"), *flags]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and message in error


def test_a_checkpoint_folder_is_not_a_run(family_tokenizer_run, tmp_path):
    step_folder = next((family_tokenizer_run / "checkpoints").iterdir())
    with pytest.raises(ConfigError, match="the scratch arm trains a fresh tokenizer with the run's config"):
        evaluate_fewshot(
            step_folder, HOST, tmp_path / "x", target=TARGET, seeds=[0], counts=[4], steps=1, eval_images=2
        )


def test_the_command_writes_its_files_and_refuses_to_overwrite_them(
    family_tokenizer_run, family_clusters, tmp_path, capsys
):
    out = tmp_path / "fewshot"
    args = [
        "--no-progress",
        "evaluate",
        "fewshot",
        "--run",
        str(family_tokenizer_run),
        "--out",
        str(out),
        "--n",
        "4",
        "--steps",
        "1",
        "--scratch-steps",
        "1",
        "--eval-images",
        "2",
        "--seeds",
        "3",
        "--families",
        str(family_clusters),
    ]
    assert main(args) == 0
    printed = capsys.readouterr().out
    result = json.loads((out / "fewshot.json").read_text())
    assert result["experiment"] == "fewshot" and result["seeds"] == [3] and result["provenance"]["wall_seconds"] > 0
    assert {row["arm"] for row in result["rows"]} == {SCRATCH, ZERO_SHOT, SHOTS_ALONE, "mixed 1:5", BACKGROUND}
    assert (out / "fewshot.png").stat().st_size > 10_000
    assert "| 4 | mixed 1:5 | 24 |" in printed and f"-> {out} (fewshot.json, fewshot.md, fewshot.png" in printed
    before = (out / "fewshot.json").read_text()
    assert main(args) == 2
    assert f"{out} already holds a fewshot experiment; pass --overwrite" in capsys.readouterr().err
    assert (out / "fewshot.json").read_text() == before

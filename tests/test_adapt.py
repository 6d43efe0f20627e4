"""Few-shot adaptation (`vqtouch adapt`): the adapted checkpoint and its header, the
mixed set's composition, the contact check's closed form and every bad input's one-line error."""

import json

import pytest
import torch

import generator_runs
from vqtouch.core import load_plugins, read_metadata
from vqtouch.plugins.cli.app import main
from vqtouch.plugins.utils.images import save_png
from vqtouch.plugins.adaptation.adapt_images import contact_fraction, family_images, target_images
from vqtouch.plugins.adaptation.families import SensorFamilies, sensor_images

HOST = load_plugins(autoload=False)


def _variant(name, seed, **variant):
    return json.dumps({"name": name, "variant": {"seed": seed, **variant}})


@pytest.fixture(scope="module")
def tokenizer_folder(tmp_path_factory):
    return generator_runs.tiny_tokenizer_folder(tmp_path_factory.mktemp("tok"))


@pytest.fixture(scope="module")
def families_folder(tokenizer_folder, tmp_path_factory):
    out = tmp_path_factory.mktemp("families")
    gelsight_v1 = _variant("gelsight", 1, colour_gain=[1.05, 0.95, 0.95])
    sensors = ["gelsight", gelsight_v1, "digit", _variant("digit", 2, noise_std=0.02)]
    assert main(generator_runs.cluster_args(tokenizer_folder, out, sensors, image_size=32)) == 0
    return out


def _adapt(tokenizer_folder, families_folder, out, images, *extra):
    return main(
        [
            "adapt",
            "--run",
            str(tokenizer_folder),
            "--families",
            str(families_folder),
            "--images",
            images,
            "--out",
            str(out),
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
            *extra,
        ]
    )


def test_adapt_writes_its_own_tokenizer_whose_header_names_the_family_and_the_shots(
    tokenizer_folder, families_folder, tmp_path, capsys
):
    from vqtouch.plugins.tokenizer import load_tokenizer, reconstruct_all

    target = _variant("gelsight", 7, illumination_shift=0.04, noise_std=0.01)
    out = tmp_path / "adapted"
    # An untrained tokenizer's families are tight: a generous threshold (refusals are tested below).
    assert _adapt(tokenizer_folder, families_folder, out, target, "--threshold", "1") == 0
    clusters = json.loads((families_folder / "cluster.json").read_text())
    gelsight_family = clusters["sensor_family"]["gelsight"]
    summary = json.loads((out / "adapt.json").read_text())
    assert summary["family"] == gelsight_family and not summary["assignment"]["refused"]
    assert summary["members_used"] == ["gelsight", "gelsight/v1"] and summary["family_images"] == 8
    assert summary["family_held_out"]["images"] == 4 and 0 < summary["family_held_out"]["after"]["ssim"] <= 1
    for file in ("autoencoder.safetensors", "quantizer.safetensors"):
        header = read_metadata(out / file)
        assert header["adaptation.family"] == str(gelsight_family) and header["adaptation.shots"] == "4"
        assert header["adaptation.ratio"] == "2" and json.loads(header["adaptation.target"])["variant"]["seed"] == 7
        assert json.loads(header["adaptation.family_members"]) == ["gelsight", "gelsight/v1"]
    assert (out / "before_after.png").is_file()
    original, _ = load_tokenizer(tokenizer_folder, HOST)
    adapted, _ = load_tokenizer(out, HOST)
    before_weights, after_weights = original.autoencoder.state_dict(), adapted.autoencoder.state_dict()
    assert before_weights.keys() == after_weights.keys()
    assert not all(torch.equal(before_weights[key], after_weights[key]) for key in before_weights)
    # The "before" score is the family tokenizer on the held-out images, recomputed here directly.
    _, _, _, held_out = target_images(target, HOST, shots=4, eval_images=4, image_size=32, seed=0)
    ssim = HOST.build("metric", {"name": "ssim"})
    ssim.update(reconstruct_all(original, held_out), held_out)
    assert summary["before"]["ssim"] == pytest.approx(ssim.compute(), abs=1e-4)
    # Beside it, the sensor's no-contact render, scored on the same images and on their contact region.
    flat = HOST.build("sensor_family", json.loads(target)).render(
        torch.zeros(1, 32, 32), generator=torch.Generator().manual_seed(0)
    )
    psnr = HOST.build("metric", {"name": "psnr"})
    psnr.update(flat.expand_as(held_out), held_out)
    assert summary["background"] == "the sensor's rendering of no contact"
    for moment in ("before", "after"):
        assert summary[moment]["background_psnr"] == pytest.approx(psnr.compute(), abs=1e-3)
        assert {"contact_psnr", "background_contact_psnr", "contact_fraction"} <= set(summary[moment])
    printed = capsys.readouterr().out
    assert "held-out gelsight/v7 (4 images): SSIM" in printed and "real frames" not in printed  # not a variant's
    assert _adapt(tokenizer_folder, families_folder, out, target) == 2
    assert "already holds an adapted tokenizer; choose another --out or pass --overwrite" in capsys.readouterr().err


def test_the_mixed_set_draws_evenly_from_the_family_but_the_unseen_sensor():
    sources = [
        '{"name": "gelsight"}',
        _variant("gelsight", 1, noise_std=0.02),
        '{"name": "digit"}',
        _variant("gelsight", 2, colour_gain=[1.1, 1, 1]),
    ]
    summary = {
        "sensors": [{"name": f"s{i}", "source": source, "images": 4} for i, source in enumerate(sources)],
        "sensor_family": {"s0": 0, "s1": 0, "s2": 1, "s3": 0},
    }
    families = SensorFamilies(summary, clusterer=None, prototypes_SF=torch.zeros(4, 2))
    images, members = family_images(families, 0, HOST, count=7, image_size=16, seed=3, exclude=sources[3])
    assert members == ["s0", "s1"] and images.shape == (7, 3, 16, 16)
    torch.testing.assert_close(
        images[:4], sensor_images(sources[0], HOST, count=4, image_size=16, seed=3 + 1009).images
    )
    torch.testing.assert_close(
        images[4:], sensor_images(sources[1], HOST, count=3, image_size=16, seed=3 + 2018).images
    )


def test_contact_fraction_is_the_share_of_pixels_off_the_background():
    images = torch.full((4, 3, 10, 10), 0.5)
    for index in range(4):  # each image presses a different 2 x (index + 1) patch: the median stays background
        images[index, :, 2 * index : 2 * index + 2, : index + 1] += 0.2
    torch.testing.assert_close(contact_fraction(images), torch.tensor([0.02, 0.04, 0.06, 0.08], dtype=torch.float64))
    images[3, :, 6:8, :4] = 0.5 + 0.03  # below the contact threshold: no longer a contact
    assert float(contact_fraction(images)[3]) == 0.0


def _frames(folder, images):
    folder.mkdir()
    for index, image in enumerate(images):
        save_png(image, folder / f"frame_{index:02d}.png")
    return folder


def test_adapt_bad_inputs_get_one_line_errors(tokenizer_folder, families_folder, tmp_path, capsys):
    gelsight = HOST.build("sensor_family", "gelsight")
    contacts = sensor_images("gelsight", HOST, count=6, image_size=32).images
    no_contact = gelsight.render(torch.zeros(6, 32, 32), generator=torch.Generator().manual_seed(0))
    one = _frames(tmp_path / "one", contacts[:1])
    three = _frames(tmp_path / "three", contacts[:3])
    mixed_sizes = _frames(tmp_path / "sizes", contacts[:3])
    save_png(torch.rand(3, 40, 32), mixed_sizes / "frame_99.png")
    corrupt = _frames(tmp_path / "corrupt", contacts[:5])
    (corrupt / "frame_03.png").write_bytes(b"not a png")
    flat = _frames(tmp_path / "flat", no_contact)
    digit = HOST.build("sensor_family", "digit")  # with DIGIT's published camera noise (7/255)
    noisy_flat = _frames(
        tmp_path / "noisy_flat", digit.render(torch.zeros(6, 32, 32), generator=torch.Generator().manual_seed(0))
    )
    cases = [
        (one, [], "1 image(s); adaptation needs the shots plus at least one held-out image"),
        (three, [], "--shots 4: the folder " + str(three) + " holds 3 images; use at most 2 shots"),
        (mixed_sizes, ["--shots", "1"], "images of different sizes (frame_00.png is 32x32, frame_99.png is 32x40)"),
        (corrupt, [], "cannot decode image " + str(corrupt / "frame_03.png")),
        (flat, [], "the 6 images look like no-contact frames"),
        (noisy_flat, [], "the 6 images look like no-contact frames"),
        (_frames(tmp_path / "ok", contacts), ["--threshold", "0"], "ok matches no sensor family: "),
        (tmp_path / "ok", ["--family", "5"], "--family 5: the families are numbered 0 to 1"),
    ]
    for folder, extra, message in cases:
        capsys.readouterr()
        assert _adapt(tokenizer_folder, families_folder, tmp_path / "out", str(folder), *extra) == 2, message
        err = capsys.readouterr().err
        assert err.startswith("vqtouch: error: ") and message in err and err.count("\n") == 1, err
        assert not (tmp_path / "out" / "autoencoder.safetensors").exists()
    # A forced family adapts a sensor the threshold refuses, and says so.
    assert (
        _adapt(
            tokenizer_folder,
            families_folder,
            tmp_path / "out",
            str(tmp_path / "ok"),
            "--threshold",
            "0",
            "--family",
            "1",
            "--shots",
            "3",
        )
        == 0
    )
    summary = json.loads((tmp_path / "out" / "adapt.json").read_text())
    assert summary["forced_family"] and summary["assignment"]["refused"] and summary["family"] == 1
    # A folder holds no no-contact frame: its background is the per-pixel median of its images.
    assert summary["background"].startswith("the per-pixel median of")
    assert {"background_psnr", "contact_psnr", "background_contact_psnr"} <= set(summary["after"])


def test_families_from_another_tokenizer_are_refused(families_folder, tmp_path, capsys):
    other = generator_runs.tiny_tokenizer_folder(tmp_path)
    assert _adapt(other, families_folder, tmp_path / "out", "gelsight") == 2
    assert "were fitted on the features of" in capsys.readouterr().err


def test_a_generator_trains_on_an_adapted_tokenizers_codes(tokenizer_folder, families_folder, tmp_path, capsys):
    from generator_runs import train_args
    from vqtouch.plugins.generator import load_pipeline
    from vqtouch.plugins.tokenizer import tokenizer_configs

    adapted = tmp_path / "adapted"
    assert _adapt(tokenizer_folder, families_folder, adapted, "gelsight", "--threshold", "1") == 0
    run = tmp_path / "gen"
    assert main(train_args(run, flags=("--tokenizer", str(adapted)))) == 0
    config = json.loads((run / "config.json").read_text())
    autoencoder, quantizer, image_size = tokenizer_configs(adapted)
    assert config["generator"]["tokenizer_run"] == str(adapted.resolve()) and config["stages"] == ["generator"]
    assert config["tokenizer"]["autoencoder"] == autoencoder and config["tokenizer"]["quantizer"] == quantizer
    assert config["data"]["image_size"] == image_size == 32
    pipeline = load_pipeline(run)
    images = pipeline(label=0, n=2, steps=2, seed=0)
    assert images.shape == (2, 3, 32, 32) and torch.isfinite(images).all()


def test_an_adapted_tokenizer_is_evaluated_on_a_dataset_it_is_given(
    tokenizer_folder, families_folder, tmp_path, capsys
):
    """`evaluate reconstruction --run ADAPT_OUT --dataset D`: the adapted tokenizer scored on D whole, as an
    independent reconstruction of D's images scores it; without --dataset, one line says what to add."""
    from vqtouch.core import Assembly, resolve_config
    from vqtouch.plugins.tokenizer import load_tokenizer, reconstruct_all

    adapted = tmp_path / "adapted"
    assert _adapt(tokenizer_folder, families_folder, adapted, "gelsight", "--threshold", "1") == 0
    capsys.readouterr()
    evaluate = ["--no-progress", "evaluate", "reconstruction", "--run", str(adapted)]
    assert main(evaluate) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and "outside any run" in error and "--dataset" in error
    block = {"name": "procedural", "num_samples": 6, "seed": 5}
    assert main([*evaluate, "--dataset", json.dumps(block), "--metrics", "ssim,psnr"]) == 0
    result = json.loads((adapted / "evaluation_dataset.json").read_text())
    assert result["checkpoint"] == str(adapted) and result["split"] == "dataset"
    config = resolve_config("reconstruction", [], ["data.image_size=32"], host=HOST)
    dataset = Assembly(config, HOST).dataset(block)
    images = torch.stack([dataset[i]["tactile"] for i in range(len(dataset))])
    tokenizer, _ = load_tokenizer(adapted, HOST)
    metric = HOST.build("metric", "psnr")
    metric.update(reconstruct_all(tokenizer, images).detach(), images)
    assert result["psnr"] == pytest.approx(float(metric.compute()), abs=1e-3)
    assert "background_psnr" in result and (adapted / "reconstructions_dataset.png").is_file()


def test_decoder_only_adaptation_keeps_every_images_codes_and_changes_only_the_decoder(
    tokenizer_folder, families_folder, tmp_path
):
    from vqtouch.plugins.tokenizer import load_tokenizer

    out = tmp_path / "decoder"
    assert _adapt(tokenizer_folder, families_folder, out, "gelsight", "--threshold", "1", "--part", "decoder") == 0
    before, _ = load_tokenizer(tokenizer_folder, HOST)
    after, _ = load_tokenizer(out, HOST)
    images = sensor_images("digit", HOST, count=4, image_size=32, seed=9).images
    with torch.no_grad():
        assert torch.equal(before.encode_codes(images), after.encode_codes(images))
        codes = before.encode_codes(images)
        assert not torch.equal(before.decode_codes(codes), after.decode_codes(codes))
    decoder = {id(p) for p in after.decoder_parameters()}
    moved = {
        name
        for (name, old), (_, new) in zip(before.autoencoder.named_parameters(), after.autoencoder.named_parameters())
        if not torch.equal(old, new)
    }
    named = dict(after.autoencoder.named_parameters())
    assert moved and all(id(named[name]) in decoder for name in moved)
    assert read_metadata(out / "autoencoder.safetensors")["adaptation.part"] == "decoder"
    assert json.loads((out / "adapt.json").read_text())["part"] == "decoder"


def test_decoder_parameters_are_those_a_decode_uses(tokenizer_folder):
    from vqtouch.plugins.tokenizer import load_tokenizer

    tokenizer, _ = load_tokenizer(tokenizer_folder, HOST)
    decoder = {id(p) for p in tokenizer.decoder_parameters()}
    names = {name for name, p in tokenizer.autoencoder.named_parameters() if id(p) in decoder}
    everything = {name for name, _ in tokenizer.autoencoder.named_parameters()}
    # An independent reference: the VQGAN's own module split.
    assert names and names < everything
    assert all(name.startswith(("dec_", "post_quant")) for name in names), sorted(names)[:5]
    assert all(name in names for name in everything if name.startswith(("dec_", "post_quant")))


def _psnr(tokenizer, images):
    from vqtouch.plugins.tokenizer import reconstruct_all

    metric = HOST.build("metric", "psnr")
    metric.update(reconstruct_all(tokenizer, images).detach(), images)
    return float(metric.compute())


def test_reconstruct_and_cluster_read_an_adapted_tokenizer(tokenizer_folder, families_folder, tmp_path, capsys):
    """An adapt output is a tokenizer wherever one is read (train generator and evaluate: the tests
    above): `reconstruct` uses its weights, not the family's, and `cluster` records it with its digest."""
    from vqtouch.plugins.tokenizer import load_tokenizer, tokenizer_digest

    adapted = tmp_path / "adapted"
    assert _adapt(tokenizer_folder, families_folder, adapted, "gelsight", "--threshold", "1") == 0
    out = tmp_path / "rec"
    assert main(["reconstruct", "--run", str(adapted), "--real-frames", "gelsight", "--out", str(out)]) == 0
    record = json.loads((out / "reconstruct.json").read_text())
    frames = HOST.build("sensor_family", HOST.validate("sensor_family", {"name": "gelsight"})).reference_frames(32, 32)
    adapted_psnr = _psnr(load_tokenizer(adapted, HOST)[0], frames)
    family_psnr = _psnr(load_tokenizer(tokenizer_folder, HOST)[0], frames)
    assert record["checkpoint"] == str(adapted) and record["images"] == len(frames)
    assert record["psnr"] == pytest.approx(adapted_psnr, abs=1e-3) and abs(adapted_psnr - family_psnr) > 1e-3

    clusters = tmp_path / "clusters"
    cluster = generator_runs.cluster_args(adapted, clusters, ["gelsight", "digit"], images=6, image_size=32)
    assert main(cluster) == 0
    summary = json.loads((clusters / "cluster.json").read_text())
    assert summary["tokenizer"] == str(adapted.resolve())
    assert summary["tokenizer_sha256"] == tokenizer_digest(adapted) != tokenizer_digest(tokenizer_folder)


def test_a_forced_family_that_is_not_the_nearest_is_noted_when_it_dominates_the_mix(
    tokenizer_folder, families_folder, tmp_path, capsys
):
    """Another family's images wash out a faint sensor's contact at 1:5 (docs/results.md), so adapt says
    so when --family forces one the sensor is not nearest to and the mix gives it more than the shots."""
    assert _adapt(tokenizer_folder, families_folder, tmp_path / "free", "gelsight", "--threshold", "1") == 0
    nearest = json.loads((tmp_path / "free" / "adapt.json").read_text())["assignment"]["family"]
    assert "note: family" not in capsys.readouterr().out
    for family, ratio, noted in ((1 - nearest, "2", True), (1 - nearest, "1", False), (nearest, "2", False)):
        out = tmp_path / f"f{family}_r{ratio}"
        forced = ["--threshold", "1", "--family", str(family), "--ratio", ratio]
        assert _adapt(tokenizer_folder, families_folder, out, "gelsight", *forced) == 0
        printed = capsys.readouterr().out
        assert (f"note: family {family} is not the one gelsight is nearest to (family {nearest})" in printed) is noted

"""Evaluation protocols: the published 512-px protocol and the default one, pairing by id, and
``vqtouch evaluate pairs`` end to end."""

import json
import math

import pytest
import torch
import torch.nn.functional as F

from vqtouch.core import ConfigError, load_plugins
from vqtouch.plugins.cli.app import main
from vqtouch.plugins.utils.images import save_png
from vqtouch.plugins.evaluation.protocols import PROTOCOLS, get_protocol, pair_by_id


def smooth_images(count: int, size: int, seed: int = 0) -> torch.Tensor:
    coarse = torch.rand(count, 3, 4, 4, generator=torch.Generator().manual_seed(seed))
    return F.interpolate(coarse, size=(size, size), mode="bilinear", align_corners=False)


def test_the_published_protocol_is_the_papers(host):
    published = get_protocol("published")
    assert published.image_size == 512
    assert [dict(metric) for metric in published.metrics] == [
        {"name": "ssim"},
        {"name": "psnr", "pooled": True},
        {"name": "lpips", "backbone": "vgg"},
    ]
    metrics = published.build_metrics(host)
    ssim = metrics.metrics["ssim"]
    assert (ssim.data_range, ssim.window_size, ssim.sigma) == (1.0, 11, 1.5)
    assert metrics.metrics["psnr"].pooled and metrics.metrics["psnr"].data_range == 1.0


def test_prepare_resizes_to_the_protocols_size_and_keeps_values_in_range():
    images = smooth_images(2, 64)
    images[:, :, :8] = 1.0  # a saturated edge: bicubic overshoots there unless clamped
    prepared = get_protocol("published").prepare(images)
    assert prepared.shape == (2, 3, 512, 512) and prepared.min() >= 0 and prepared.max() <= 1
    assert get_protocol("default").prepare(images) is images


def test_the_two_protocols_agree_where_they_must(host):
    """At 512 px with the same error in every pair, SSIM is the same number under both protocols and
    the published pooled PSNR equals the default per-image mean."""
    real = smooth_images(2, 512, seed=3) * 0.9  # room for the offset: no clamping, the same error everywhere
    generated = real + 0.05
    published, default = get_protocol("published"), get_protocol("default")
    published_scores = published.score(published.build_metrics(host), generated, real)
    default_metrics = default.build_metrics(host)
    default_metrics.metrics = {name: default_metrics.metrics[name] for name in ("ssim", "psnr")}
    default_scores = default.score(default_metrics, generated, real)
    assert published_scores["ssim"] == pytest.approx(default_scores["ssim"], abs=1e-4)
    assert published_scores["psnr"] == pytest.approx(default_scores["psnr"], abs=1e-3)
    assert published_scores["psnr"] == pytest.approx(10 * math.log10(1 / 0.05**2), abs=1e-3)


def test_the_protocols_disagree_where_they_should(host):
    """Pooled PSNR is not the mean of per-image PSNRs when the pairs' errors differ."""
    real = smooth_images(2, 512, seed=3) * 0.8
    generated = real + torch.tensor([0.01, 0.1]).view(2, 1, 1, 1)
    published, default = get_protocol("published"), get_protocol("default")
    pooled = published.score(published.build_metrics(host), generated, real)["psnr"]
    default_metrics = default.build_metrics(host)
    default_metrics.metrics = {"psnr": default_metrics.metrics["psnr"]}
    mean = default.score(default_metrics, generated, real)["psnr"]
    assert pooled == pytest.approx(10 * math.log10(1 / ((0.01**2 + 0.1**2) / 2)), abs=1e-3)
    assert mean == pytest.approx(30.0, abs=1e-3) and pooled < mean - 5


def test_without_weights_lpips_is_listed_as_skipped_never_scored(host, monkeypatch):
    monkeypatch.delenv("VQTOUCH_LPIPS_VGG", raising=False)
    published = get_protocol("published")
    real = smooth_images(2, 64)
    scores = published.score(published.build_metrics(host), real, real)
    assert "lpips" not in scores and "vgg16-397923af.pth" in scores["skipped"]["lpips"]


def test_unknown_protocol_and_unknown_override_are_one_line_errors(host):
    with pytest.raises(
        ConfigError,
        match="unknown evaluation protocol 'publishd'.*available: default, published.*did you mean 'published'",
    ):
        get_protocol("publishd")
    with pytest.raises(ConfigError, match="protocol 'published' has no metric 'fid'"):
        get_protocol("published").build_metrics(host, {"fid": {"weights": "x"}})


def test_pairs_are_matched_by_id_and_mismatches_named():
    assert pair_by_id({"b": 1, "a": 2}, {"a": 3, "b": 4}) == ["a", "b"]
    with pytest.raises(
        ConfigError,
        match=r"1 generated image\(s\) without a real one \(c\); 1 real image\(s\) "
        r"without a generated one \(d\)",
    ):
        pair_by_id({"a": 1, "c": 2}, {"a": 3, "d": 4})


def _write_folder(folder, images, names):
    for image, name in zip(images, names):
        save_png(image, folder / f"{name}.png")


def test_evaluate_pairs_scores_folders_by_file_name(tmp_path, capsys):
    real, generated = smooth_images(3, 64, seed=1), smooth_images(3, 64, seed=1) * 0.9
    names = ["run1/0001", "run1/0002", "run2/0001"]
    _write_folder(tmp_path / "real", real, names)
    # The generated folder lists the same ids in another order, so pairing by position would mismatch.
    _write_folder(tmp_path / "generated", generated.flip(0), names[::-1])
    out = tmp_path / "scores.json"
    assert (
        main(
            [
                "evaluate",
                "pairs",
                "--generated",
                str(tmp_path / "generated"),
                "--real",
                str(tmp_path / "real"),
                "--protocol",
                "default",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    result = json.loads(out.read_text())
    assert result["protocol"] == "default" and result["pairs"] == 3 and result["image_size"] == [64, 64]
    expected = get_protocol("default").build_metrics(load_plugins(autoload=False))
    expected.metrics = {name: expected.metrics[name] for name in ("ssim", "psnr")}
    reference = expected.score(generated, real)
    assert result["ssim"] == pytest.approx(reference["ssim"], abs=2e-3)  # the PNGs are 8-bit
    assert "lpips" in result["skipped"] and "fd_effnetlite0" in result and "kid_effnetlite0" in result
    assert "skipped lpips: " in capsys.readouterr().out


def test_evaluate_pairs_names_unmatched_files_in_one_line(tmp_path, capsys):
    _write_folder(tmp_path / "real", smooth_images(2, 32), ["a", "b"])
    _write_folder(tmp_path / "generated", smooth_images(2, 32), ["a", "c"])
    assert (
        main(["evaluate", "pairs", "--generated", str(tmp_path / "generated"), "--real", str(tmp_path / "real")]) == 2
    )
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and "(c)" in error and "(b)" in error
    assert main(["evaluate", "pairs", "--generated", str(tmp_path / "nowhere"), "--real", str(tmp_path / "real")]) == 2
    assert "is not a folder of images" in capsys.readouterr().err


def test_every_protocol_builds(host):
    for protocol in PROTOCOLS.values():
        assert len(protocol.build_metrics(host)) == len(protocol.metrics)

"""The metrics (torchmetrics underneath): closed forms, independent references, invariants, skipping.

Each weighted metric runs here on files of the real layout with random tensors (tests/metric_weights.py):
that checks every loader and computation, not pretrained numbers.
"""

import math

import pytest
import torch
import torch.nn.functional as F

import metric_weights
from vqtouch.core import BuildContext, SkippedMetric
from vqtouch.plugins.evaluation.metric_set import MetricSet
from vqtouch.plugins.evaluation import inception_metrics, metrics

CONTEXT = BuildContext()


def smooth_images(count: int, size: int = 32, seed: int = 0) -> torch.Tensor:
    """Random colour fields (4x4, bilinearly upsampled): image-like, not white noise."""
    coarse = torch.rand(count, 3, 4, 4, generator=torch.Generator().manual_seed(seed))
    return F.interpolate(coarse, size=(size, size), mode="bilinear", align_corners=False)


def with_noise(images: torch.Tensor, sigma: float, seed: int = 1) -> torch.Tensor:
    return (images + sigma * torch.randn(images.shape, generator=torch.Generator().manual_seed(seed))).clamp(0, 1)


def score(metric, predicted, target) -> float:
    metric.reset()
    metric.update(predicted, target)
    return metric.compute()


# -- PSNR -----------------------------------------------------------------------------------------


def test_psnr_closed_form(host):
    target = torch.full((1, 3, 16, 16), 0.5, dtype=torch.float64)
    # torchmetrics divides in float32: agreement to its precision.
    assert score(host.build("metric", "psnr", CONTEXT), target + 0.1, target) == pytest.approx(20.0, rel=1e-6)


def test_psnr_averages_per_image_and_pooled_psnr_pools_the_error(host):
    target = torch.zeros(2, 3, 8, 8, dtype=torch.float64)
    predicted = torch.stack([torch.full((3, 8, 8), 0.1), torch.full((3, 8, 8), 0.01)]).double()  # MSE 1e-2 and 1e-4
    assert score(host.build("metric", "psnr", CONTEXT), predicted, target) == pytest.approx(30.0, rel=1e-6)
    pooled = host.build("metric", {"name": "psnr", "pooled": True}, CONTEXT)
    assert score(pooled, predicted, target) == pytest.approx(10 * math.log10(1 / ((1e-2 + 1e-4) / 2)), rel=1e-6)


@pytest.mark.parametrize("pooled", [False, True])
def test_psnr_of_identical_images_is_capped_not_infinite(host, pooled):
    images = torch.zeros(1, 3, 8, 8)
    assert score(host.build("metric", {"name": "psnr", "pooled": pooled}, CONTEXT), images, images) == 100.0


def test_psnr_data_range_scales_the_peak(host):
    target = torch.zeros(1, 3, 8, 8, dtype=torch.float64)
    psnr_255 = host.build("metric", {"name": "psnr", "data_range": 255.0}, CONTEXT)
    assert score(psnr_255, target + 25.5, target) == pytest.approx(20.0, rel=1e-6)


# -- SSIM -----------------------------------------------------------------------------------------


def reference_ssim(x: torch.Tensor, y: torch.Tensor, window: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Wang et al.'s SSIM written out (float64, Gaussian window) as torchmetrics defines its mean: over every
    pixel, the images reflect-padded by half a window, negative variances from round-off clamped to 0.
    The reference torchmetrics' number must equal, per image."""
    half = (window - 1) // 2
    x, y = (F.pad(images.double(), (half, half, half, half), mode="reflect") for images in (x, y))
    coords = torch.arange(window, dtype=torch.float64) - (window - 1) / 2
    gauss = torch.exp(-(coords**2) / (2 * sigma**2))
    gauss = gauss / gauss.sum()
    kernel = (gauss[:, None] * gauss[None, :]).expand(x.shape[1], 1, -1, -1)

    def blur(images):
        return F.conv2d(images, kernel, groups=x.shape[1])

    c1, c2 = 0.01**2, 0.03**2
    mu_x, mu_y = blur(x), blur(y)
    var_x, var_y = (blur(x * x) - mu_x**2).clamp_min(0), (blur(y * y) - mu_y**2).clamp_min(0)
    cov = blur(x * y) - mu_x * mu_y
    ssim_map = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2))
    return ssim_map.flatten(1).mean(1)


@pytest.mark.parametrize("shape", [(3, 3, 32, 32), (2, 3, 24, 40), (1, 1, 11, 11)])
def test_ssim_equals_the_written_out_definition(host, shape):
    target = torch.rand(shape, generator=torch.Generator().manual_seed(4))
    predicted = with_noise(target, 0.1)
    ssim = host.build("metric", "ssim", CONTEXT)
    torch.testing.assert_close(ssim.per_image(predicted, target), reference_ssim(predicted, target), rtol=0, atol=1e-12)


@pytest.mark.parametrize("value", [0.0, 1.0, 0.37])
def test_ssim_of_constant_and_saturated_images(host, value):
    metric = host.build("metric", "ssim", CONTEXT)
    images = torch.full((1, 3, 16, 16), value)
    assert score(metric, images, images) == pytest.approx(1.0, abs=1e-12)
    opposite = score(metric, 1 - images, images)
    assert math.isfinite(opposite) and opposite <= 1.0


def test_ssim_matches_closed_form_for_constant_images(host):
    # Constant images a, b: the variance terms vanish, SSIM = (2ab + C1) / (a^2 + b^2 + C1).
    a, b, c1 = 0.3, 0.6, 0.01**2
    value = score(host.build("metric", "ssim", CONTEXT), torch.full((1, 1, 16, 16), a), torch.full((1, 1, 16, 16), b))
    assert value == pytest.approx((2 * a * b + c1) / (a * a + b * b + c1), rel=1e-6)


@pytest.mark.parametrize("name", ["ssim", "ms_ssim", "psnr"])
def test_similarity_is_symmetric_and_falls_as_noise_grows(host, name):
    metric = host.build("metric", name, CONTEXT)
    target = smooth_images(2, 64)
    values = [score(metric, with_noise(target, sigma), target) for sigma in (0.0, 0.02, 0.05, 0.1, 0.2)]
    assert all(a > b for a, b in zip(values, values[1:])), values
    noisy = with_noise(target, 0.05)
    assert score(metric, noisy, target) == pytest.approx(score(metric, target, noisy), abs=1e-12)


# -- MS-SSIM --------------------------------------------------------------------------------------


@pytest.mark.parametrize("side, scales", [(32, 2), (64, 3), (128, 4), (175, 4), (176, 5), (512, 5)])
def test_ms_ssim_uses_as_many_scales_as_the_size_allows(side, scales):
    assert metrics.ms_ssim_scales(side, side) == scales


def test_ms_ssim_with_one_scale_is_ssim(host):
    target = smooth_images(3, 48)
    predicted = with_noise(target, 0.05)
    one_scale = host.build("metric", {"name": "ms_ssim", "scales": 1}, CONTEXT)
    torch.testing.assert_close(
        one_scale.per_image(predicted, target), reference_ssim(predicted, target), rtol=0, atol=1e-12
    )


def test_ms_ssim_is_one_for_identical_images_and_refuses_too_small_ones(host):
    images = smooth_images(2, 64)
    assert score(host.build("metric", "ms_ssim", CONTEXT), images, images) == pytest.approx(1.0, abs=1e-12)
    with pytest.raises(ValueError, match="needs larger images"):
        host.build("metric", {"name": "ms_ssim", "scales": 5}, CONTEXT).update(images, images)


def test_ms_ssim_of_opposite_images_is_a_number_not_nan(host):
    images = smooth_images(2, 64)
    assert 0.0 <= score(host.build("metric", "ms_ssim", CONTEXT), 1 - images, images) < 0.5


# -- LPIPS ----------------------------------------------------------------------------------------


@pytest.fixture
def lpips_vgg(host, tmp_path_factory, monkeypatch):
    options = metric_weights.weighted_metric_options(("metric", "lpips"), tmp_path_factory.getbasetemp(), monkeypatch)
    return host.build("metric", {"name": "lpips", **options}, CONTEXT)


def test_lpips_is_zero_for_identical_images_symmetric_and_grows_with_noise(lpips_vgg):
    target = smooth_images(2, 32)
    values = [score(lpips_vgg, with_noise(target, sigma), target) for sigma in (0.0, 0.05, 0.1, 0.2)]
    assert values[0] == pytest.approx(0.0, abs=1e-7)
    assert all(a < b for a, b in zip(values, values[1:])), values
    noisy = with_noise(target, 0.1)
    assert score(lpips_vgg, noisy, target) == pytest.approx(score(lpips_vgg, target, noisy), rel=1e-6)


def test_lpips_alexnet_equals_the_tokenizers_independent_lpips_loss(host, tmp_path_factory, monkeypatch):
    """torchmetrics' LPIPS and vqtouch's own LpipsLoss (written from the paper for training, with the
    NaN-free normalisation) give the same distance from the same AlexNet trunk and heads."""
    from torchmetrics.functional.image import lpips as torchmetrics_lpips

    from vqtouch.plugins.evaluation import feature_networks
    from vqtouch.plugins.tokenizer.perceptual import LpipsLoss

    trunk = metric_weights.fabricated_torchvision(tmp_path_factory.getbasetemp(), "alexnet")
    heads = torchmetrics_lpips.__file__.replace("lpips.py", "lpips_models/alex.pth")
    metric_weights.accept_fabricated(monkeypatch, metrics, "LPIPS_TRUNK_WEIGHTS", "alex", trunk)
    metric_weights.accept_fabricated(monkeypatch, feature_networks, "ALEXNET_WEIGHTS", None, trunk)
    metric = host.build("metric", {"name": "lpips", "backbone": "alex", "weights": str(trunk)}, CONTEXT)
    target = smooth_images(3, 64)
    predicted = with_noise(target, 0.1)
    expected = LpipsLoss(backbone_path=str(trunk), heads_path=heads)(predicted * 2 - 1, target * 2 - 1)
    torch.testing.assert_close(metric.per_image(predicted, target).float(), expected, rtol=1e-4, atol=1e-6)


def test_lpips_without_weights_is_skipped_naming_the_file(host, monkeypatch):
    monkeypatch.delenv("VQTOUCH_LPIPS_VGG", raising=False)
    metric = host.build("metric", "lpips", CONTEXT)
    assert isinstance(metric, SkippedMetric) and not metric.higher_is_better
    for needed in (
        "vgg16-397923af.pth",
        "VQTOUCH_LPIPS_VGG",
        "https://download.pytorch.org/models/vgg16-397923af.pth",
        "never downloads",
    ):
        assert needed in metric.skipped
    with pytest.raises(Exception, match="skipped"):
        metric.update(torch.zeros(1, 3, 16, 16), torch.zeros(1, 3, 16, 16))


def test_lpips_refuses_a_file_of_another_network(host, tmp_path_factory, monkeypatch):
    alexnet = metric_weights.fabricated_torchvision(tmp_path_factory.getbasetemp(), "alexnet")
    metric_weights.accept_fabricated(monkeypatch, metrics, "LPIPS_TRUNK_WEIGHTS", "vgg", alexnet)
    metric = host.build("metric", {"name": "lpips", "weights": str(alexnet)}, CONTEXT)
    assert isinstance(metric, SkippedMetric) and "not torchvision's ImageNet weights" in metric.skipped


def test_lpips_checks_the_real_files_sha256(host, tmp_path_factory):
    vgg = metric_weights.fabricated_torchvision(tmp_path_factory.getbasetemp(), "vgg16")
    metric = host.build("metric", {"name": "lpips", "weights": str(vgg)}, CONTEXT)
    assert isinstance(metric, SkippedMetric) and "expected a digest starting with 397923af" in metric.skipped


# -- the metric set: skipped metrics are reported, never scored --------------------------------------


def test_metric_set_reports_skipped_metrics_with_their_reason_and_no_number(host, monkeypatch):
    monkeypatch.delenv("VQTOUCH_FID_INCEPTION", raising=False)
    metric_set = MetricSet(
        [("ssim", host.build("metric", "ssim", CONTEXT)), ("fid", host.build("metric", "fid", CONTEXT))]
    )
    images = smooth_images(2, 32)
    scores = metric_set.score(images, images, prefix="background_")
    assert scores["background_ssim"] == pytest.approx(1.0)
    assert "fid" not in scores and "background_fid" not in scores
    assert "weights-inception-2015-12-05-6726825d.pth" in scores["skipped"]["fid"]


def test_a_skipped_metric_needs_a_reason():
    with pytest.raises(ValueError, match="needs a reason"):
        SkippedMetric("  ")


# -- FID and KID ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def inception_file(tmp_path_factory):
    return metric_weights.fabricated_inception(tmp_path_factory.getbasetemp())


def test_fid_is_zero_for_identical_sets_symmetric_grows_with_noise_and_is_the_features_frechet_distance(
    host, inception_file
):
    """FID's invariants, and torchmetrics' FID equals vqtouch's row-space Fréchet distance
    (fd_effnetlite0's computation, written independently) on the same Inception features."""
    from vqtouch.plugins.evaluation.fd_metric import feature_frechet_distance

    fid = host.build("metric", {"name": "fid", "weights": str(inception_file)}, CONTEXT)
    real = smooth_images(6, 32)
    slightly, strongly = with_noise(real, 0.1), with_noise(real, 0.3)
    slight_fid = score(fid, slightly, real)
    assert abs(score(fid, real, real)) < 1e-4 * slight_fid
    assert 0 < slight_fid < score(fid, strongly, real)
    assert slight_fid == pytest.approx(score(fid, real, slightly), rel=1e-6)
    with torch.no_grad():
        features_real, features_slightly = (fid.metric.inception(images).double() for images in (real, slightly))
    assert slight_fid == pytest.approx(feature_frechet_distance(features_slightly, features_real), rel=1e-4)


def unbiased_polynomial_mmd(x: torch.Tensor, y: torch.Tensor) -> float:
    """KID's statistic written out: unbiased MMD^2 with k(a, b) = (a.b / d + 1)^3."""
    d = x.shape[1]

    def kernel(a, b):
        return (a @ b.T / d + 1) ** 3

    n, m = len(x), len(y)
    k_xx, k_yy, k_xy = kernel(x, x), kernel(y, y), kernel(x, y)
    return float(
        (k_xx.sum() - k_xx.diag().sum()) / (n * (n - 1))
        + (k_yy.sum() - k_yy.diag().sum()) / (m * (m - 1))
        - 2 * k_xy.mean()
    )


def test_kid_effnetlite0_is_the_unbiased_polynomial_mmd_of_fd_effnetlite0s_features(host):
    kid = host.build("metric", {"name": "kid_effnetlite0", "image_size": 32, "subsets": 3}, CONTEXT)
    real, generated = smooth_images(5, 32, seed=1), with_noise(smooth_images(5, 32, seed=1), 0.2)
    value = score(kid, generated, real)  # subset size = all 5 images: every subset is the whole set
    features = kid.metric.inception
    expected = unbiased_polynomial_mmd(features(real), features(generated))
    assert value == pytest.approx(expected, rel=1e-6)
    assert score(kid, generated, real) == value  # seeded subsets: the same number again


def test_kid_subsets_are_seeded(host):
    real, generated = smooth_images(8, 32, seed=1), smooth_images(8, 32, seed=2)
    values = []
    for seed in (0, 0, 1):
        kid = host.build(
            "metric",
            {"name": "kid_effnetlite0", "image_size": 32, "subsets": 4, "subset_size": 4, "seed": seed},
            CONTEXT,
        )
        values.append(score(kid, generated, real))
    assert values[0] == values[1] != values[2]


def test_distribution_metrics_need_two_images_of_each_set(host):
    kid = host.build("metric", {"name": "kid_effnetlite0", "image_size": 32}, CONTEXT)
    kid.update(smooth_images(1, 32), smooth_images(1, 32))
    with pytest.raises(ValueError, match="at least 2 generated and 2 real"):
        kid.compute()


def test_fid_and_kid_without_weights_are_skipped_naming_the_file(host, monkeypatch):
    monkeypatch.delenv("VQTOUCH_FID_INCEPTION", raising=False)
    for name in ("fid", "kid"):
        metric = host.build("metric", name, CONTEXT)
        assert isinstance(metric, SkippedMetric)
        assert "weights-inception-2015-12-05-6726825d.pth" in metric.skipped
        assert "VQTOUCH_FID_INCEPTION" in metric.skipped


def test_fid_refuses_a_file_of_another_network(host, tmp_path_factory):
    vgg = metric_weights.fabricated_torchvision(tmp_path_factory.getbasetemp(), "vgg16")
    metric = host.build("metric", {"name": "fid", "weights": str(vgg)}, CONTEXT)
    assert isinstance(metric, SkippedMetric) and "does not hold torch-fidelity's Inception-v3 weights" in metric.skipped


def test_inception_metrics_see_uint8_like_torchmetrics_fid():
    class Recorder(torch.nn.Module):
        def forward(self, images):
            self.seen = images
            return torch.zeros(len(images), 2048)

    recorder = Recorder()
    inception_metrics.Uint8Inception(recorder)(torch.tensor([0.0, 0.5, 1.0, 1.2]).view(1, 1, 2, 2).expand(1, 3, 2, 2))
    assert recorder.seen.dtype == torch.uint8 and recorder.seen[0, 0].flatten().tolist() == [0, 127, 255, 255]


# -- input checks ---------------------------------------------------------------------------------


def test_metrics_reject_bad_input(host):
    psnr = host.build("metric", "psnr", CONTEXT)
    with pytest.raises(ValueError, match="equal shape"):
        psnr.update(torch.zeros(1, 3, 8, 8), torch.zeros(1, 3, 8, 9))
    with pytest.raises(ValueError, match="NaN or Inf"):
        psnr.update(torch.full((1, 3, 8, 8), float("nan")), torch.zeros(1, 3, 8, 8))
    with pytest.raises(ValueError, match="no images were added"):
        psnr.compute()
    ssim = host.build("metric", "ssim", CONTEXT)
    with pytest.raises(ValueError, match="at least 11 px"):
        ssim.update(torch.zeros(1, 3, 8, 8), torch.zeros(1, 3, 8, 8))


def test_ssim_window_must_be_odd(host):
    with pytest.raises(ValueError, match="must be odd"):
        host.build("metric", {"name": "ssim", "window_size": 8}, CONTEXT)

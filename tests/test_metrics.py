import math

import pytest
import torch

from vqtouch.core import BuildContext

CONTEXT = BuildContext()


@pytest.mark.parametrize("name", ["psnr", "ssim"])
def test_metric_contract_identical_images_are_best(host, name):
    metric = host.build("metric", name, CONTEXT)
    images = torch.rand(2, 3, 32, 32)
    metric.update(images, images)
    best = metric.compute()
    metric.reset()
    metric.update((images + 0.1 * torch.randn_like(images)).clamp(0, 1), images)
    assert best > metric.compute()


def test_psnr_closed_form(host):
    metric = host.build("metric", "psnr", CONTEXT)
    target = torch.full((1, 3, 16, 16), 0.5)
    predicted = target + 0.1  # MSE = 0.01 -> PSNR = 20 dB exactly
    metric.update(predicted, target)
    assert metric.compute() == pytest.approx(20.0, abs=1e-5)


def test_psnr_averages_per_image(host):
    metric = host.build("metric", "psnr", CONTEXT)
    target = torch.zeros(2, 3, 8, 8)
    predicted = torch.stack([torch.full((3, 8, 8), 0.1), torch.full((3, 8, 8), 0.01)])  # 20 dB and 40 dB
    metric.update(predicted, target)
    assert metric.compute() == pytest.approx(30.0, abs=1e-4)


def test_psnr_of_identical_images_is_capped_not_infinite(host):
    metric = host.build("metric", "psnr", CONTEXT)
    images = torch.zeros(1, 3, 8, 8)
    metric.update(images, images)
    assert metric.compute() == pytest.approx(100.0)


@pytest.mark.parametrize("value", [0.0, 1.0, 0.37])
def test_ssim_of_constant_and_saturated_images(host, value):
    metric = host.build("metric", "ssim", CONTEXT)
    images = torch.full((1, 3, 16, 16), value)
    metric.update(images, images)
    assert metric.compute() == pytest.approx(1.0, abs=1e-9)
    metric.reset()
    metric.update(1 - images, images)  # black vs white is maximally different in luminance
    assert math.isfinite(metric.compute()) and metric.compute() <= 1.0


def test_ssim_matches_closed_form_for_constant_offset(host):
    # Constant images a, b: sigma terms vanish, SSIM = (2ab + C1) / (a^2 + b^2 + C1).
    metric = host.build("metric", "ssim", CONTEXT)
    a, b, c1 = 0.3, 0.6, 0.01**2
    metric.update(torch.full((1, 1, 16, 16), a), torch.full((1, 1, 16, 16), b))
    assert metric.compute() == pytest.approx((2 * a * b + c1) / (a * a + b * b + c1), rel=1e-9)


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

"""Sensor families: contract over the registry, numerical extremes, variants, sim-vs-real fidelity."""

import sys

import pytest
import torch

from vqtouch.core import PluginError, SensorFamily, load_plugins
from vqtouch.sensors.variants import SensorVariant, apply_variant

HOST = load_plugins(autoload=False)
FAMILIES = HOST.registry("sensor_family").names()


def sphere_press(size: int, fov_mm: float, radius_mm: float = 2.0, contact_mm: float = 1.5) -> torch.Tensor:
    axis = (torch.arange(size) + 0.5) / size * fov_mm - fov_mm / 2
    y, x = torch.meshgrid(axis, axis, indexing="ij")
    cap = (radius_mm**2 - x**2 - y**2).clamp_min(0).sqrt() - (radius_mm**2 - contact_mm**2) ** 0.5
    return cap.clamp_min(0)


def test_the_three_builtin_families_are_registered():
    assert {"gelsight", "gelsight_mini", "digit"} <= set(FAMILIES)


@pytest.mark.parametrize("name", FAMILIES)
@pytest.mark.parametrize("batch", [1, 3])
def test_render_contract(name, batch):
    sensor = HOST.build("sensor_family", name)
    assert isinstance(sensor, SensorFamily) and sensor.field_of_view_mm > 0
    heights = torch.stack([sphere_press(48, sensor.field_of_view_mm) * (k + 1) / batch for k in range(batch)])
    images = sensor.render(heights)
    assert images.shape == (batch, 3, 48, 48) and images.dtype == torch.float32
    assert torch.isfinite(images).all() and images.min() >= 0 and images.max() <= 1
    assert (images[-1] - sensor.render(torch.zeros(1, 48, 48))[0]).abs().max() > 0.05  # the contact shows


@pytest.mark.parametrize("name", FAMILIES)
def test_flat_gel_is_the_background(name):
    sensor = HOST.build("sensor_family", name)
    flat = sensor.render(torch.zeros(2, 32, 40))
    torch.testing.assert_close(flat[0], sensor.background(32, 40, torch.device("cpu")).clamp(0, 1))
    torch.testing.assert_close(flat[0], flat[1])


@pytest.mark.parametrize("name", FAMILIES)
@pytest.mark.parametrize("depth_mm", [1e-4, 5.0, 50.0])
def test_extreme_depths_stay_finite_and_in_range(name, depth_mm):
    sensor = HOST.build("sensor_family", name)
    heights = torch.zeros(1, 32, 32)
    heights[:, 8:24, 8:24] = depth_mm  # a flat-topped punch: infinite-looking slopes at its walls
    images = sensor.render(heights)
    assert torch.isfinite(images).all() and images.min() >= 0 and images.max() <= 1


@pytest.mark.parametrize("name", FAMILIES)
def test_bad_height_maps_are_clear_errors(name):
    sensor = HOST.build("sensor_family", name)
    with pytest.raises(ValueError, match=r"shape \(B, H, W\)"):
        sensor.render(torch.zeros(32, 32))
    with pytest.raises(ValueError, match="NaN or Inf"):
        sensor.render(torch.full((1, 8, 8), float("nan")))
    with pytest.raises(ValueError, match=">= 0 mm"):
        sensor.render(-torch.ones(1, 8, 8))


@pytest.mark.parametrize("name", FAMILIES)
def test_render_is_deterministic_for_a_generator(name):
    sensor = HOST.build("sensor_family", {"name": name, "variant": {"noise_std": 0.05}})
    heights = sphere_press(32, sensor.field_of_view_mm)[None]
    first = sensor.render(heights, generator=torch.Generator().manual_seed(3))
    again = sensor.render(heights, generator=torch.Generator().manual_seed(3))
    other = sensor.render(heights, generator=torch.Generator().manual_seed(4))
    assert torch.equal(first, again) and not torch.equal(first, other)


@pytest.mark.parametrize("name", FAMILIES)
def test_resolution_independent_physical_scale(name):
    sensor = HOST.build("sensor_family", name)
    coarse = sensor.render(sphere_press(32, sensor.field_of_view_mm)[None])
    fine = sensor.render(sphere_press(128, sensor.field_of_view_mm)[None])
    fine_down = torch.nn.functional.interpolate(fine, size=(32, 32), mode="area")
    assert (coarse - fine_down).abs().mean() < 0.03


@pytest.mark.gpu
@pytest.mark.parametrize("name", FAMILIES)
def test_render_on_gpu_matches_cpu(name):
    sensor = HOST.build("sensor_family", name)
    heights = sphere_press(64, sensor.field_of_view_mm)[None]
    torch.testing.assert_close(sensor.to("cuda").render(heights.cuda()).cpu(), sensor.to("cpu").render(heights),
                               atol=2e-3, rtol=0)


# -- variants ----------------------------------------------------------------------------------

def test_identity_variant_changes_nothing():
    images = torch.rand(2, 3, 16, 16)
    assert apply_variant(images, SensorVariant()) is images


@pytest.mark.parametrize("option", [
    {"illumination_shift": 0.1}, {"colour_gain": (1.2, 1.0, 0.8)}, {"background_drift": 0.1},
    {"response_scale": 0.5}, {"wear_blur": 0.03}, {"damage_spots": 3}, {"noise_std": 0.05},
    {"shift": (0.05, 0.0)}, {"rotation_deg": 5.0},
])
def test_each_variant_factor_changes_the_image(option):
    base = HOST.build("sensor_family", "gelsight")
    derived = HOST.build("sensor_family", {"name": "gelsight", "variant": option})
    heights = sphere_press(48, base.field_of_view_mm)[None]
    generator = torch.Generator().manual_seed(0)
    difference = (derived.render(heights, generator) - base.render(heights)).abs().mean()
    assert difference > 1e-3, option


def test_variant_fixed_pattern_is_the_same_sensor_every_time():
    config = {"name": "digit", "variant": {"damage_spots": 4, "background_drift": 0.1, "seed": 11}}
    one, two = HOST.build("sensor_family", config), HOST.build("sensor_family", config)
    heights = torch.zeros(1, 32, 32)
    assert torch.equal(one.render(heights), two.render(heights))
    reseeded = HOST.build("sensor_family", {**config, "variant": {**config["variant"], "seed": 12}})
    assert not torch.equal(one.render(heights), reseeded.render(heights))


def test_variant_options_are_bounded():
    from vqtouch.core import ConfigError

    with pytest.raises(ConfigError, match="variant.noise_std"):
        HOST.build("sensor_family", {"name": "gelsight", "variant": {"noise_std": 2}})


def test_missing_taxim_is_a_clear_error(monkeypatch):
    from vqtouch.sensors.gelsight import calibration_folder

    monkeypatch.setitem(sys.modules, "taxim", None)
    with pytest.raises(PluginError, match="pip install taxim"):
        calibration_folder("gelsight")


# -- fidelity against taxim's real frames -------------------------------------------------------

@pytest.mark.parametrize("sensor, min_ssim, min_psnr", [("gelsight", 0.94, 29.0), ("gelsight_mini", 0.81, 23.3)])
def test_render_matches_real_ball_presses(sensor, min_ssim, min_psnr):
    """Measured: GelSight SSIM 0.953 / PSNR 29.9 dB, Mini 0.826 / 23.8 dB (64 px contact crops)."""
    from vqtouch.sensors.fidelity import evaluate_fidelity

    result = evaluate_fidelity(sensor, HOST, resolution=(240, 320), crop_px=64)
    assert result.ssim >= min_ssim and result.psnr >= min_psnr, result.summary()
    # Drawing the contact must beat drawing nothing at all.
    assert result.ssim > result.background_ssim + 0.05 and result.psnr > result.background_psnr + 3.0


def test_rgb_channel_order_matches_the_real_frames(monkeypatch):
    """taxim's frames are BGR and its grad_r table is blue: swapping either must hurt."""
    from vqtouch.sensors.fidelity import evaluate_fidelity

    good = evaluate_fidelity("gelsight", HOST, resolution=(120, 160), crop_px=32)
    sensor = HOST.build("sensor_family", {"name": "gelsight", "view": "full"})
    sensor.table_K36 = sensor.table_K36.flip(1)
    original_build = HOST.build
    monkeypatch.setattr(HOST, "build", lambda kind, config, context=None:
                        sensor if kind == "sensor_family" else original_build(kind, config, context))
    swapped = evaluate_fidelity("gelsight", HOST, resolution=(120, 160), crop_px=32)
    assert good.psnr > swapped.psnr + 2.0

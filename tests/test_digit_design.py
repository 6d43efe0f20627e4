"""The digit family follows DIGIT's published design, read from tacto's config_digit.yml
(tacto is installed with --no-deps and never imported), and falls back to its built-in
values, warning once, when that file is missing."""

import math
import sys
import warnings

import pytest
import torch

import vqtouch.sensors.digit as digit_sensor
from vqtouch.core import PluginError, load_plugins

HOST = load_plugins(autoload=False)
PUBLISHED_AZIMUTHS = (-150.0, -30.0, 90.0)  # red upper left, green upper right, blue down (image azimuths)


@pytest.fixture
def tacto_yaml():
    """tacto's config_digit.yml, parsed here with PyYAML directly."""
    import yaml

    path = digit_sensor.tacto_config_path()
    assert path is not None, "tacto is not installed: pip install --no-deps tacto==0.0.3 (the Makefile does)"
    return yaml.safe_load(path.read_text())


def _clean_digit(**options):
    """The default digit family without camera noise (so shading is compared exactly)."""
    return HOST.build("sensor_family", {"name": "digit", "camera_noise_std": 0.0, **options})


# -- reading the file ---------------------------------------------------------------------------


def test_tacto_file_is_located_without_importing_tacto():
    assert "tacto" not in sys.modules
    path = digit_sensor.tacto_config_path()
    assert path is not None and path.name == "config_digit.yml" and path.parent.name == "tacto"
    HOST.build("sensor_family", "digit")
    assert "tacto" not in sys.modules  # importing it would need pyrender and OpenGL


def test_design_values_are_the_files(tacto_yaml):
    """Each design value against the YAML, derived here by hand for the file's camera orientation
    [90, 0, -90] (camera looks along +x; image right = -y, image down = -z)."""
    sensor = tacto_yaml["sensor"]
    camera, gel, lights = sensor["camera"][0], sensor["gel"], sensor["lights"]
    assert camera["orientation"] == [90, 0, -90] and lights["polar"] is True
    design = digit_sensor.read_tacto_design(digit_sensor.tacto_config_path())

    thetas, radii, xs = lights["xrtheta"]["thetas"], lights["xrtheta"]["rs"], lights["xrtheta"]["xs"]
    # A light at (y, z) = r (cos t, sin t) sits at (column, row) = -r (cos t, sin t) in the image: azimuth t + 180.
    expected_azimuths = [(t + 180 + 180) % 360 - 180 for t in thetas]
    in_front_of_gel = [gel["origin"][0] - (lights["origin"][0] + x) for x in xs]
    expected_elevations = [math.degrees(math.atan2(depth, r)) for depth, r in zip(in_front_of_gel, radii)]
    distance = gel["origin"][0] - camera["position"][0]
    seen = 2 * distance * math.tan(math.radians(camera["yfov"]) / 2)
    assert design.led_azimuth_deg == pytest.approx(expected_azimuths, abs=1e-9)
    assert design.led_elevation_deg == pytest.approx(expected_elevations, abs=1e-9)
    assert design.led_colours == tuple(
        tuple(float(c) * i for c in colour) for colour, i in zip(lights["colors"], lights["intensities"])
    )
    assert design.camera_noise_std == sensor["noise"]["color"]["std"] / 255
    assert design.field_of_view_mm == pytest.approx(1000 * min(gel["width"], gel["height"], seen))
    # The values docs/guide.md and the module docstring cite.
    assert design.led_azimuth_deg == pytest.approx(PUBLISHED_AZIMUTHS, abs=1e-9)
    assert design.led_elevation_deg == pytest.approx((40.3645,) * 3, abs=1e-4)
    assert design.led_colours == ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    assert design.camera_noise_std == pytest.approx(7 / 255) and design.field_of_view_mm == pytest.approx(20.0)


def test_polar_and_cartesian_light_positions_agree(tacto_yaml):
    """The file states the lights twice (polar and, rounded, cartesian): both give the same design."""
    polar = digit_sensor.design_from_tacto_config(tacto_yaml)
    tacto_yaml["sensor"]["lights"]["polar"] = False
    cartesian = digit_sensor.design_from_tacto_config(tacto_yaml)
    assert cartesian.led_azimuth_deg == pytest.approx(polar.led_azimuth_deg, abs=0.01)
    assert cartesian.led_elevation_deg == pytest.approx(polar.led_elevation_deg, abs=0.01)


@pytest.mark.parametrize(
    "old, new, message",
    [
        ("noise:", "noises:", "missing entry 'noise'"),
        ("yfov: 60", "yfov: [60", "line|column|unterminated"),  # a YAML syntax error, whichever parser reads it
    ],
)
def test_a_broken_design_file_is_a_one_line_error(tmp_path, old, new, message):
    path = tmp_path / "config_digit.yml"
    path.write_text(digit_sensor.tacto_config_path().read_text().replace(old, new))
    with pytest.raises(PluginError, match=rf"cannot read DIGIT's design from .*({message}).*design='builtin'") as info:
        digit_sensor.read_tacto_design(path)
    assert "\n" not in str(info.value)


# -- the renderer uses it -----------------------------------------------------------------------


def test_default_digit_renders_the_published_design():
    sensor = HOST.build("sensor_family", "digit")
    design = digit_sensor.read_tacto_design(digit_sensor.tacto_config_path())
    assert sensor.design == design and sensor.field_of_view_mm == design.field_of_view_mm
    assert sensor.camera_noise_std == design.camera_noise_std
    assert torch.equal(sensor.colour_L3, torch.tensor(design.led_colours))
    light = sensor.light_L3.double()
    azimuths = torch.rad2deg(torch.atan2(light[:, 1], light[:, 0]))
    elevations = torch.rad2deg(torch.asin(light[:, 2]))
    assert azimuths.tolist() == pytest.approx(design.led_azimuth_deg, abs=1e-4)
    assert elevations.tolist() == pytest.approx(design.led_elevation_deg, abs=1e-4)


def test_flat_gel_noise_std_is_7_over_255():
    noisy = HOST.build("sensor_family", "digit")
    flat = torch.zeros(4, 64, 64)
    noise = noisy.render(flat, generator=torch.Generator().manual_seed(0)) - _clean_digit().render(flat)
    # 49152 samples: the sample std's standard error is 0.3 %; the background is far from 0 and 1, so no clipping.
    assert float(noise.std()) == pytest.approx(7 / 255, rel=0.02)
    assert abs(float(noise.mean())) < 1e-3
    again = noisy.render(flat, generator=torch.Generator().manual_seed(0)) - _clean_digit().render(flat)
    assert torch.equal(noise, again)  # drawn from the generator


def test_light_colours_show_in_the_shading_of_a_press():
    """A sphere pressed into the gel brightens each channel on the side facing its light: red the
    upper left, green the upper right, blue the lower side (the published light positions)."""
    sensor = _clean_digit()
    size, fov = 96, sensor.field_of_view_mm
    axis = (torch.arange(size) + 0.5) / size * fov - fov / 2
    rows, cols = torch.meshgrid(axis, axis, indexing="ij")
    press = ((16 - rows**2 - cols**2).clamp_min(0).sqrt() - 3).clamp_min(0)[None]  # 4 mm ball, 1 mm deep
    response = (sensor.render(press) - sensor.render(torch.zeros_like(press)))[0]
    for channel, expected in enumerate(PUBLISHED_AZIMUTHS):
        weight = response[channel].clamp_min(0)
        angle = math.degrees(math.atan2(float((weight * rows).sum()), float((weight * cols).sum())))
        assert abs((angle - expected + 180) % 360 - 180) < 10, (channel, angle, expected)


def test_explicit_options_override_the_design():
    sensor = HOST.build(
        "sensor_family",
        {
            "name": "digit",
            "field_of_view_mm": 16.0,
            "led_elevation_deg": 25.0,
            "led_azimuth_deg": 90.0,
            "camera_noise_std": 0.01,
        },
    )
    assert sensor.field_of_view_mm == 16.0 and sensor.camera_noise_std == 0.01
    light = sensor.light_L3.double()
    assert torch.rad2deg(torch.atan2(light[:, 1], light[:, 0])).tolist() == pytest.approx([90, -150, -30], abs=1e-4)
    assert torch.rad2deg(torch.asin(light[:, 2])).tolist() == pytest.approx([25] * 3, abs=1e-4)


# -- without tacto's file -----------------------------------------------------------------------


def test_missing_tacto_falls_back_to_builtin_and_warns_once(monkeypatch):
    monkeypatch.setattr(digit_sensor, "tacto_config_path", lambda: None)
    monkeypatch.setattr(digit_sensor, "_warned_missing_tacto", False)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sensors = [HOST.build("sensor_family", "digit") for _ in range(3)]
    messages = [str(w.message) for w in caught if "tacto" in str(w.message)]
    assert len(messages) == 1 and "pip install --no-deps tacto==0.0.3" in messages[0], messages
    for sensor in sensors:
        assert sensor.design == digit_sensor.BUILTIN_DESIGN
        assert sensor.field_of_view_mm == 16.0 and sensor.camera_noise_std == 0.0
    images = sensors[0].render(torch.rand(2, 32, 32), generator=torch.Generator().manual_seed(0))
    assert images.shape == (2, 3, 32, 32) and torch.isfinite(images).all()
    # The fallback is exactly the built-in design.
    builtin = HOST.build("sensor_family", {"name": "digit", "design": "builtin"})
    heights = torch.rand(1, 32, 32)
    assert torch.equal(sensors[0].render(heights), builtin.render(heights))


def test_builtin_design_needs_no_file_and_does_not_warn(monkeypatch):
    monkeypatch.setattr(digit_sensor, "tacto_config_path", lambda: pytest.fail("the builtin design read tacto"))
    monkeypatch.setattr(digit_sensor, "_warned_missing_tacto", False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sensor = HOST.build("sensor_family", {"name": "digit", "design": "builtin"})
    assert sensor.design == digit_sensor.BUILTIN_DESIGN

"""Writing a sensor family as a third party: the public API, the surface-effects step of
``RenderedSensor.render``, and the example ``marker_gel`` family (tests/example_plugin)."""

import ast
import json
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
import torch

import vqtouch.sensors as public
from vqtouch.core import PluginConfig, SensorFamily, load_plugins

EXAMPLE = Path(__file__).parent / "example_plugin"
MARKER_MODULE = EXAMPLE / "vqtouch_example_plugin" / "marker_sensor.py"
AUTHORING_KIT = [
    "RenderedSensor",
    "SensorVariant",
    "apply_variant",
    "check_height_map",
    "drifted_background",
    "environment_variant",
    "gaussian_blur",
    "surface_slopes",
]

# Grid geometry for the marker tests: 18 mm imaged at 108 px is 1/6 mm a pixel, so the default
# 1.5 mm marker pitch is 9 px and the markers' centres, at (k + 1/2) pitches, fall exactly on
# the centres of pixels 4, 13, 22, ...; pixels 8, 17, ... lie halfway between two markers.
SIZE, FIRST, PITCH_PX = 108, 4, 9
MARKERS = (slice(None), slice(None), slice(FIRST, None, PITCH_PX), slice(FIRST, None, PITCH_PX))
BETWEEN = (slice(None), slice(None), slice(FIRST + 4, None, PITCH_PX), slice(FIRST + 4, None, PITCH_PX))


@pytest.fixture(scope="module")
def host():
    """A host with the marker plugin loaded the way a user would name an extra plugin module."""
    sys.path.insert(0, str(EXAMPLE))
    try:
        yield load_plugins(autoload=False, extra=["vqtouch_example_plugin.marker_sensor"])
    finally:
        sys.path.remove(str(EXAMPLE))


def press(size: int = SIZE, fov_mm: float = 18.0, radius_mm: float = 4.0, contact_mm: float = 3.0) -> torch.Tensor:
    """One spherical press (1, size, size) in mm at the centre of the field of view."""
    axis = (torch.arange(size) + 0.5) / size * fov_mm - fov_mm / 2
    y, x = torch.meshgrid(axis, axis, indexing="ij")
    cap = (radius_mm**2 - x**2 - y**2).clamp_min(0).sqrt() - (radius_mm**2 - contact_mm**2) ** 0.5
    return cap.clamp_min(0)[None]


# -- the public API ---------------------------------------------------------------------------


def test_public_api_exports_the_authoring_kit_documented():
    assert sorted(public.__all__) == AUTHORING_KIT
    for name in AUTHORING_KIT:
        exported = getattr(public, name)
        assert exported.__doc__ and exported.__doc__.strip(), name
    assert issubclass(public.RenderedSensor, SensorFamily)
    for method in ("background", "contact_response", "surface_effects", "render", "pixel_size_mm"):
        assert getattr(public.RenderedSensor, method).__doc__, method
    # sensor_id and field_of_view_mm come from the contract, not a second declaration.
    assert "sensor_id" not in vars(public.RenderedSensor) and "field_of_view_mm" not in vars(public.RenderedSensor)
    assert public.RenderedSensor.reference_frames is SensorFamily.reference_frames


def test_public_api_import_is_light():
    # The public names load on first use: importing the package (as the built-in families' plugin
    # modules do) imports none of its sub-modules, no calibration data and no torch.
    code = (
        "import sys, vqtouch.sensors; "
        "print(sorted(m for m in sys.modules if m in ('taxim', 'torch') or m.startswith('vqtouch.sensors.')))"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert result.stdout.split("\n")[0] == "[]"


def test_marker_plugin_imports_only_the_public_api():
    tree = ast.parse(MARKER_MODULE.read_text())
    modules = {node.module for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)}
    modules |= {alias.name for node in ast.walk(tree) if isinstance(node, ast.Import) for alias in node.names}
    vqtouch_modules = {module for module in modules if module.split(".")[0] == "vqtouch"}
    assert vqtouch_modules == {"vqtouch.core", "vqtouch.sensors"}


def test_marker_plugin_has_its_own_entry_point():
    project = tomllib.loads((EXAMPLE / "pyproject.toml").read_text())["project"]
    assert project["entry-points"]["vqtouch"]["example-markers"] == "vqtouch_example_plugin.marker_sensor"


def test_installed_package_registers_marker_gel_through_its_entry_point(run_cli, example_plugin_site):
    result = run_cli(
        "plugins", "--json", python_path=example_plugin_site, env_extra={"VQTOUCH_DISABLE_PLUGIN_AUTOLOAD": ""}
    )
    assert result.returncode == 0, result.stderr
    rows = {(row["kind"], row["name"]): row for row in json.loads(result.stdout)}
    row = rows[("sensor_family", "marker_gel")]
    assert row["plugin"] == "example-markers" and row["package"] == "vqtouch-example-plugin"


# -- the marker_gel family ----------------------------------------------------------------------


def test_marker_config_is_strict_documented_and_bounded(host):
    from vqtouch.core import ConfigError

    model = host.registry("sensor_family").get("marker_gel").config_model
    assert issubclass(model, PluginConfig) and model().name == "marker_gel"
    assert model.model_fields["variant"].annotation is public.SensorVariant
    assert all(info.description for info in model.model_fields.values())
    with pytest.raises(ConfigError, match="marker_pitch_mm"):
        host.build("sensor_family", {"name": "marker_gel", "marker_pitch_mm": 0.0})
    with pytest.raises(ConfigError, match="marker_colour"):
        host.build("sensor_family", {"name": "marker_gel", "marker_colour": (0.1, 0.1, 2.0)})


@pytest.mark.parametrize("batch", [1, 3])
def test_marker_gel_renders_images_in_range(host, batch):
    sensor = host.build("sensor_family", "marker_gel")
    assert isinstance(sensor, public.RenderedSensor) and sensor.sensor_id == "marker_gel"
    heights = torch.cat([press(48) * (k + 1) / batch for k in range(batch)])
    images = sensor.render(heights)
    assert images.shape == (batch, 3, 48, 48) and images.dtype == torch.float32
    assert torch.isfinite(images).all() and images.min() >= 0 and images.max() <= 1
    assert (images[-1] - sensor.render(torch.zeros(1, 48, 48))[0]).abs().max() > 0.05  # the contact shows
    extreme = torch.zeros(1, 32, 32)
    extreme[:, 8:24, 8:24] = 50.0
    assert torch.isfinite(sensor.render(extreme)).all()


def test_markers_are_dark_dots_on_the_gel(host):
    sensor = host.build("sensor_family", "marker_gel")
    flat = sensor.render(torch.zeros(1, SIZE, SIZE))
    background = sensor.background(SIZE, SIZE, torch.device("cpu")).unsqueeze(0)
    ink = torch.tensor(sensor.config.marker_colour)[None, :, None, None]
    markers, between = flat[MARKERS], flat[BETWEEN]
    assert markers.shape[-2:] == (12, 12)  # the whole 12 x 12 grid
    torch.testing.assert_close(markers, ink.expand_as(markers))  # a marker's centre is all ink
    torch.testing.assert_close(between, background[BETWEEN])  # halfway between markers: bare gel
    assert (markers.mean(1) < between.mean(1) - 0.5).all()  # every marker darker than its surroundings
    dark = (flat.mean(1) < 0.5).float().mean()  # ink covers about pi r^2 / pitch^2 of the gel
    assert 0.05 < dark < 0.15


def test_markers_move_with_the_slope_of_the_gel(host):
    sensor = host.build("sensor_family", "marker_gel")
    sigma_px = sensor.gel_blur_mm / min(sensor.pixel_size_mm(SIZE, SIZE))
    smoothed = public.gaussian_blur(press().unsqueeze(1), sigma_px).squeeze(1)
    flat, pressed = sensor.marker_coverage(torch.zeros_like(smoothed)), sensor.marker_coverage(smoothed)
    # Around the contact's rim the dots have slid; in the untouched corners they have not.
    assert (pressed - flat).abs()[..., 20:88, 20:88].sum() > 20
    torch.testing.assert_close(pressed[..., :12, :12], flat[..., :12, :12])
    none = host.build("sensor_family", {"name": "marker_gel", "marker_shift_mm": 0.0})
    torch.testing.assert_close(none.marker_coverage(smoothed), flat)


def test_a_variant_changes_the_marker_gel(host):
    base = host.build("sensor_family", "marker_gel")
    heights = press(48)
    for option in ({"colour_gain": (1.2, 1.0, 0.8)}, {"rotation_deg": 5.0}, {"noise_std": 0.05}):
        derived = host.build("sensor_family", {"name": "marker_gel", "variant": option})
        difference = (derived.render(heights, torch.Generator().manual_seed(0)) - base.render(heights)).abs().mean()
        assert difference > 1e-3, option


def test_surface_effects_come_before_the_variant(host):
    """The variant perturbs the markers too: a colour gain tints the ink, a shift moves the dots."""
    gain = (1.25, 1.0, 0.5)
    plain = host.build("sensor_family", "marker_gel").render(torch.zeros(1, SIZE, SIZE))
    tinted = host.build("sensor_family", {"name": "marker_gel", "variant": {"colour_gain": gain}})
    tinted = tinted.render(torch.zeros(1, SIZE, SIZE))
    gain_1311 = torch.tensor(gain)[None, :, None, None]
    torch.testing.assert_close(tinted[MARKERS], (plain[MARKERS] * gain_1311).clamp(0, 1))
    assert not torch.allclose(tinted[MARKERS], plain[MARKERS])  # the ink itself changed colour

    # A misalignment of half a pitch puts bare gel where the markers were, and ink halfway.
    shifted = host.build("sensor_family", {"name": "marker_gel", "variant": {"shift": (0.5 / 12, 0.5 / 12)}})
    shifted = shifted.render(torch.zeros(1, SIZE, SIZE))
    assert (shifted[MARKERS].mean(1) > plain[MARKERS].mean(1) + 0.5).all()
    assert (shifted[BETWEEN].mean(1)[..., :-1, :-1] < plain[BETWEEN].mean(1)[..., :-1, :-1] - 0.5).all()


# -- the surface-effects step, on a sensor written in the test ------------------------------------


class _SpySensor(public.RenderedSensor):
    """Flat grey gel, a response equal to the (smoothed) depth, and a surface effect that records its inputs."""

    field_of_view_mm = 10.0

    def __init__(self, variant: public.SensorVariant) -> None:
        super().__init__(variant, gel_blur_mm=0.5)
        self.seen: list[tuple[torch.Tensor, torch.Tensor]] = []

    def background(self, height, width, device):
        return torch.full((3, height, width), 0.5, device=device)

    def contact_response(self, height_mm_BHW):
        return height_mm_BHW.unsqueeze(1).expand(-1, 3, -1, -1)

    def surface_effects(self, images_B3HW, height_mm_BHW):
        self.seen.append((images_B3HW.clone(), height_mm_BHW.clone()))
        marked = images_B3HW.clone()
        marked[:, :, ::4, ::4] = 0.2  # a sparse grid of grey marks
        return marked


def test_render_calls_surface_effects_between_shading_and_variant():
    heights = torch.zeros(2, 16, 16)
    heights[:, 6:10, 6:10] = 0.3
    variant = public.SensorVariant(colour_gain=(2.0, 1.0, 0.5), response_scale=0.5)
    sensor = _SpySensor(variant)
    images = sensor.render(heights)
    assert len(sensor.seen) == 1
    shaded, height_seen = sensor.seen[0]
    smoothed = public.gaussian_blur(heights.unsqueeze(1), 0.5 / (10.0 / 16)).squeeze(1)
    torch.testing.assert_close(height_seen, smoothed)  # the gel-smoothed indentation
    torch.testing.assert_close(shaded, 0.5 + 0.5 * smoothed.unsqueeze(1).expand(-1, 3, -1, -1))  # not the variant
    marks = images[:, :, ::4, ::4]
    torch.testing.assert_close(marks, (0.2 * torch.tensor([2.0, 1.0, 0.5])[None, :, None, None]).expand_as(marks))
    assert public.RenderedSensor.surface_effects(sensor, shaded, height_seen) is shaded  # default: identity

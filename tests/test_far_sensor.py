"""bench/far_sensor_plugin.py's ``far_mini``: registered through ``VQTOUCH_PLUGINS``, it draws its
gradient as the no-contact image and a contact only as signed edges along its light."""

from __future__ import annotations

import math
from pathlib import Path

import torch

from vqtouch.core import load_plugins


def test_far_mini_registers_and_draws_a_gradient_with_edge_contacts(monkeypatch):
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "bench"))
    host = load_plugins(autoload=False, extra=["far_sensor_plugin"])
    sensor = host.build("sensor_family", {"name": "far_mini", "variant": {"noise_std": 0.0}})
    flat = sensor.render(torch.zeros(1, 32, 32))[0]
    top, bottom = sensor.config.top_colour, sensor.config.bottom_colour
    assert torch.allclose(flat[:, 0, :], torch.tensor(top).view(3, 1).expand(3, 32), atol=1e-6)
    assert torch.allclose(flat[:, -1, :], torch.tensor(bottom).view(3, 1).expand(3, 32), atol=1e-6)
    # A ramp rising along the light brightens every channel by edge_gain x its slope (inside, away from the
    # gel blur at the borders); one falling darkens them by as much.
    side_mm = sensor.field_of_view_mm
    columns = (torch.arange(32) + 0.5) * side_mm / 32  # pixel centres in mm
    azimuth = math.radians(sensor.config.light_azimuth_deg)
    sensor.gel_blur_mm = 0.0
    ramp = 0.01 * (columns.view(1, 1, 32) - columns.min()).expand(1, 32, 32)
    bright = sensor.render(ramp)[0] - flat
    dark = sensor.render(0.01 * side_mm - ramp)[0] - flat
    expected = sensor.config.edge_gain * math.cos(azimuth) * 0.01
    assert torch.allclose(bright[:, 8:24, 8:24], torch.full((3, 16, 16), expected), atol=1e-6)
    assert torch.allclose(dark[:, 8:24, 8:24], torch.full((3, 16, 16), -expected), atol=1e-6)

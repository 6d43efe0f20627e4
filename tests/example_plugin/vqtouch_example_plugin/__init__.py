"""Example third-party plugin: a sensor family, a conditioner, a pipeline stage, a CLI command.

Everything a plugin can do is here in under two hundred lines; see docs/extending.md.
(``marker_sensor.py`` beside it shows a sensor family built on the public ``RenderedSensor``
base class, registered through its own entry point.)
"""

from __future__ import annotations

import argparse
from typing import Literal

import torch
import torch.nn.functional as F
from pydantic import Field
from torch import nn

from vqtouch.core import Conditioner, ConfigError, PluginConfig, Section, SensorFamily, StageJob, hookimpl
from vqtouch.plugins.utils.images import image_grid, save_png


class ToySensorConfig(PluginConfig):
    """A Lambertian gel lit by one white light, with a tinted background."""

    name: Literal["toy_sensor"] = "toy_sensor"
    light_elevation_deg: float = Field(45.0, gt=0, lt=90, description="Elevation of the single light.")
    tint: tuple[float, float, float] = Field((0.9, 0.8, 0.7), description="Background colour (RGB in [0, 1]).")
    noise: float = Field(0.0, ge=0, le=0.2, description="Std of additive pixel noise.")


class ToySensor(SensorFamily):
    """Shades the height map's normals with one light and adds them to a tinted background."""

    def __init__(self, config: ToySensorConfig) -> None:
        super().__init__()
        self.config = config
        self.register_buffer("tint_C", torch.tensor(config.tint))

    def render(self, height_mm_BHW, generator=None):
        grad_y, grad_x = torch.gradient(height_mm_BHW.float(), dim=(1, 2))
        elevation = torch.deg2rad(torch.tensor(self.config.light_elevation_deg))
        shade = (torch.cos(elevation) * grad_x + torch.sin(elevation) * 1.0) / torch.sqrt(1 + grad_x**2 + grad_y**2)
        image = self.tint_C[None, :, None, None] * shade[:, None].clamp(0, 1)
        if self.config.noise:
            image = image + self.config.noise * torch.randn(image.shape, generator=generator)
        return image.clamp(0, 1)


class MeanColourConfig(PluginConfig):
    """Conditions on the mean colour of an image (a deliberately simple conditioner)."""

    name: Literal["mean_colour"] = "mean_colour"
    hidden: int = Field(32, ge=1, description="Hidden width of the projection.")


class MeanColourConditioner(Conditioner):
    sample_key = "tactile"

    def __init__(self, cond_dim: int, hidden: int) -> None:
        super().__init__(cond_dim, num_tokens=1)
        self.mlp = nn.Sequential(nn.Linear(3, hidden), nn.SiLU(), nn.Linear(hidden, cond_dim))

    def encode(self, condition):
        return self.mlp(F.adaptive_avg_pool2d(condition.float(), 1).flatten(1)).unsqueeze(1)


@hookimpl
def vqtouch_register_sensor_families(register):
    register(
        "toy_sensor",
        lambda config, context: ToySensor(config),
        ToySensorConfig,
        description="Example: one-light Lambertian gel.",
    )


@hookimpl
def vqtouch_register_conditioners(register):
    register(
        "mean_colour",
        lambda config, context: MeanColourConditioner(context.cond_dim, config.hidden),
        MeanColourConfig,
        description="Example: mean image colour as the condition.",
    )


class GallerySection(Section):
    """Options of the ``gallery`` stage (its own section of the experiment config: ``gallery.*``)."""

    depths_mm: list[float] = Field(
        [0.2, 0.5, 1.0],
        min_length=1,
        max_length=16,
        description="Press depths of the ball, in mm, one picture column each.",
    )
    radius_mm: float = Field(2.0, gt=0, le=10, description="Radius of the pressed ball in mm.")


def run_gallery(job: StageJob) -> dict:
    """Press a ball into the experiment's sensor at each depth; save the row and report mean intensities."""
    sensor = job.assembly.sensor()
    size = job.config.data.image_size
    axis = (torch.arange(size) + 0.5) / size * sensor.field_of_view_mm - sensor.field_of_view_mm / 2
    ys, xs = torch.meshgrid(axis, axis, indexing="ij")
    cap = (job.section.radius_mm**2 - xs**2 - ys**2).clamp_min(0).sqrt()
    heights = torch.stack([(cap - (job.section.radius_mm - depth)).clamp_min(0) for depth in job.section.depths_mm])
    with torch.no_grad():
        images = sensor.render(heights)
    save_png(image_grid(images, columns=len(images)), job.run.path / "gallery.png")
    return {"mean_intensity": [round(float(image.mean()), 4) for image in images], "picture": "gallery.png"}


@hookimpl
def vqtouch_register_stages(register):
    # A stage from a third-party package: its section, the slots it needs and how it runs.
    register(
        "gallery",
        run_gallery,
        section=GallerySection,
        needs=("sensor",),
        description="Example: a ball pressed at several depths into the experiment's sensor.",
    )


@hookimpl
def vqtouch_validate_experiment(config):
    # A plugin may veto combinations it cannot serve.
    uses_mean_colour = any(c.name == "mean_colour" for c in config.generator.conditioners)
    if uses_mean_colour and config.data.image_size < 16:
        raise ConfigError("conditioner 'mean_colour' needs data.image_size >= 16")


@hookimpl
def vqtouch_checkpoint_metadata(kind, name, config):
    if name == "toy_sensor":
        return {"example.calibration": "toy-v1"}
    return None


@hookimpl
def vqtouch_add_commands(subparsers):
    parser = subparsers.add_parser("example-render", help="render one sphere press with the toy sensor")
    parser.add_argument("--radius", type=float, default=0.3, help="sphere radius as a fraction of the image")
    parser.set_defaults(handler=_render_command)


def _render_command(args: argparse.Namespace) -> int:
    sensor = args.host.build("sensor_family", {"name": "toy_sensor"})
    ys, xs = torch.meshgrid(torch.linspace(-1, 1, 32), torch.linspace(-1, 1, 32), indexing="ij")
    height = (args.radius**2 - xs**2 - ys**2).clamp_min(0).sqrt()[None]
    image = sensor.render(height)
    print(f"rendered {tuple(image.shape)} mean={image.mean():.4f}")
    return 0

"""Visual images of a contact region: what an external camera sees of the touched object.

The same surface that is pressed into the gel is shaded as a material: a textured albedo
(plain, brushed metal, wood grain, speckle, threads, ink) lit by one random directional
light with ambient, Lambertian and Blinn-Phong specular terms.  Objects of different
classes therefore differ in colour, texture and shine, as the paper's visual condition needs.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from vqtouch.core.image_size import extent_hw

from .objects import Contact, ObjectClass, draw_digit


def _noise(generator: torch.Generator, size_hw: tuple[int, int], cells: int) -> torch.Tensor:
    coarse = torch.randn(1, 1, cells, cells, generator=generator)
    return F.interpolate(coarse, size=size_hw, mode="bilinear", align_corners=True)[0, 0]


def material_albedo(object_class: ObjectClass, contact: Contact, generator: torch.Generator) -> torch.Tensor:
    """(3, H, W) albedo in [0, 1] (the contact's height-map size): the class colour, jittered, with its
    material texture."""
    size_hw = tuple(contact.surface_mm_HW.shape[-2:])
    height, width = size_hw
    base = torch.tensor(object_class.albedo) * (1 + 0.15 * (torch.rand(3, generator=generator) * 2 - 1))
    texture = torch.zeros(size_hw)
    angle = math.radians(contact.angle_deg)
    y, x = torch.meshgrid(torch.linspace(-1, 1, height), torch.linspace(-1, 1, width), indexing="ij")
    along = x * math.cos(angle) + y * math.sin(angle)
    across = -x * math.sin(angle) + y * math.cos(angle)
    if object_class.texture == "brushed":
        streaks = F.interpolate(torch.randn(1, 1, 1, width, generator=generator), size=size_hw, mode="nearest")
        texture = 0.05 * streaks[0, 0]
    elif object_class.texture == "wood":
        rings = torch.sin(40 * across + 3 * _noise(generator, size_hw, 6))
        texture = 0.12 * rings
    elif object_class.texture == "speckle":
        texture = 0.12 * torch.randn(size_hw, generator=generator) + 0.1 * _noise(generator, size_hw, 16)
    elif object_class.texture == "threads":
        texture = 0.08 * torch.sin(60 * along) * torch.sin(60 * across) + 0.05 * _noise(generator, size_hw, 32)
    elif object_class.texture == "ink" and contact.detail:
        side = min(size_hw)
        half = side / 2
        ink = draw_digit(int(contact.detail), (x * half) * 0.9, (y * half) * 0.9, side * 0.6, side * 0.1)
        texture = -0.5 * ink
    return (base[:, None, None] * (1 + texture)).clamp(0, 1)


def render_visual(
    object_class: ObjectClass,
    contact: Contact,
    generator: torch.Generator,
    field_of_view_mm: float | tuple[float, float],
) -> torch.Tensor:
    """(3, H, W) visual image in [0, 1] of the contact region, shaded from the object's surface;
    ``field_of_view_mm`` as :func:`~vqtouch.sensors.objects.sample_contact` (a side, or (rows, columns))."""
    surface = contact.surface_mm_HW
    rows_mm, cols_mm = extent_hw(field_of_view_mm)
    slope_row, slope_col = torch.gradient(surface, spacing=(rows_mm / surface.shape[-2], cols_mm / surface.shape[-1]))
    normal = torch.stack([-slope_col, -slope_row, torch.ones_like(surface)])
    normal = normal / normal.norm(dim=0, keepdim=True)
    azimuth = 2 * math.pi * float(torch.rand(1, generator=generator))
    elevation = math.radians(35 + 40 * float(torch.rand(1, generator=generator)))
    light = torch.tensor(
        [math.cos(azimuth) * math.cos(elevation), math.sin(azimuth) * math.cos(elevation), math.sin(elevation)]
    )
    diffuse = (normal * light[:, None, None]).sum(0).clamp_min(0)
    halfway = light + torch.tensor([0.0, 0.0, 1.0])
    halfway = halfway / halfway.norm()
    specular = (normal * halfway[:, None, None]).sum(0).clamp_min(0) ** 40
    albedo = material_albedo(object_class, contact, generator)
    # Surfaces far below the contact fall into shadow: a soft depth cue for the camera.
    depth_shade = torch.exp(-(surface.max() - surface).clamp_min(0) / 4.0)
    image = (albedo * (0.25 + 0.75 * diffuse) + object_class.specular * specular) * (0.6 + 0.4 * depth_shade)
    return image.clamp(0, 1)

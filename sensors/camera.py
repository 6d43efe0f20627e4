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

from .objects import Contact, ObjectClass, draw_digit


def _noise(generator: torch.Generator, size: int, cells: int) -> torch.Tensor:
    coarse = torch.randn(1, 1, cells, cells, generator=generator)
    return F.interpolate(coarse, size=(size, size), mode="bilinear", align_corners=True)[0, 0]


def material_albedo(object_class: ObjectClass, contact: Contact, generator: torch.Generator) -> torch.Tensor:
    """(3, S, S) albedo in [0, 1]: the class colour, jittered, with its material texture."""
    size = contact.surface_mm_HW.shape[-1]
    base = torch.tensor(object_class.albedo) * (1 + 0.15 * (torch.rand(3, generator=generator) * 2 - 1))
    texture = torch.zeros(size, size)
    angle = math.radians(contact.angle_deg)
    axis = torch.linspace(-1, 1, size)
    y, x = torch.meshgrid(axis, axis, indexing="ij")
    along = x * math.cos(angle) + y * math.sin(angle)
    across = -x * math.sin(angle) + y * math.cos(angle)
    if object_class.texture == "brushed":
        streaks = F.interpolate(torch.randn(1, 1, 1, size, generator=generator), size=(size, size), mode="nearest")
        texture = 0.05 * streaks[0, 0]
    elif object_class.texture == "wood":
        rings = torch.sin(40 * across + 3 * _noise(generator, size, 6))
        texture = 0.12 * rings
    elif object_class.texture == "speckle":
        texture = 0.12 * torch.randn(size, size, generator=generator) + 0.1 * _noise(generator, size, 16)
    elif object_class.texture == "threads":
        texture = 0.08 * torch.sin(60 * along) * torch.sin(60 * across) + 0.05 * _noise(generator, size, 32)
    elif object_class.texture == "ink" and contact.detail:
        half = size / 2
        ink = draw_digit(int(contact.detail), (x * half) * 0.9, (y * half) * 0.9, size * 0.6, size * 0.1)
        texture = -0.5 * ink
    return (base[:, None, None] * (1 + texture)).clamp(0, 1)


def render_visual(object_class: ObjectClass, contact: Contact, generator: torch.Generator,
                  field_of_view_mm: float) -> torch.Tensor:
    """(3, S, S) visual image in [0, 1] of the contact region, shaded from the object's surface."""
    surface = contact.surface_mm_HW
    size = surface.shape[-1]
    pixel_mm = field_of_view_mm / size
    slope_row, slope_col = torch.gradient(surface, spacing=(pixel_mm, pixel_mm))
    normal = torch.stack([-slope_col, -slope_row, torch.ones_like(surface)])
    normal = normal / normal.norm(dim=0, keepdim=True)
    azimuth = 2 * math.pi * float(torch.rand(1, generator=generator))
    elevation = math.radians(35 + 40 * float(torch.rand(1, generator=generator)))
    light = torch.tensor([math.cos(azimuth) * math.cos(elevation), math.sin(azimuth) * math.cos(elevation),
                          math.sin(elevation)])
    diffuse = (normal * light[:, None, None]).sum(0).clamp_min(0)
    halfway = light + torch.tensor([0.0, 0.0, 1.0])
    halfway = halfway / halfway.norm()
    specular = (normal * halfway[:, None, None]).sum(0).clamp_min(0) ** 40
    albedo = material_albedo(object_class, contact, generator)
    # Surfaces far below the contact fall into shadow: a soft depth cue for the camera.
    depth_shade = torch.exp(-(surface.max() - surface).clamp_min(0) / 4.0)
    image = (albedo * (0.25 + 0.75 * diffuse) + object_class.specular * specular) * (0.6 + 0.4 * depth_shade)
    return image.clamp(0, 1)

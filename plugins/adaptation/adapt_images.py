"""The images an adaptation trains and scores on: the unseen sensor's shots and held-out images, the
families' images mixed with them, the no-contact backgrounds a rebase moves between, and the check that
a sensor's frames hold contacts at all.
"""

from __future__ import annotations

import json
import math
from typing import Any

import torch

from vqtouch.core import ConfigError, DatasetError, PluginHost, VqtouchError
from vqtouch.core.image_size import ImageSize, image_hw
from vqtouch.plugins.data.sensor_folders import folder_of, sensor_folder_files
from vqtouch.plugins.evaluation.contact import (
    MAX_BACKGROUND_IMAGES,
    RENDERED_BACKGROUND,
    evenly_spaced,
    median_background,
    no_contact_image,
)

from .families import SensorFamilies, sensor_images
from .stages_plugin import AdaptSettings


#: Fewer family images than this give a rebase no reliable median background: 64 more are drawn.
MIN_BACKGROUND_IMAGES = 32
#: A pixel belongs to a contact when it differs from the set's background by more than this (mean
#: absolute difference over RGB, images in [0, 1]) and than the camera noise allows: above a
#: drifting background, below a light press.
CONTACT_PIXEL_THRESHOLD = 0.04
#: A set of frames holds contacts when at least one frame has this fraction of contact pixels.
MIN_CONTACT_FRACTION = 0.002
#: The contact check looks at this many images at most (it asks whether the set holds contacts at all).
MAX_CONTACT_CHECK_IMAGES = 64


class AdaptationRefused(VqtouchError):
    """The unseen sensor cannot be adapted as asked (it matches no family, or its images hold no contact)."""


class ImageSet(torch.utils.data.Dataset):
    """Images (N, 3, S, S) in [0, 1] as tactile samples (what the tokenizer trainer reads)."""

    class_names: list[str] = []

    def __init__(self, images_N3HW: torch.Tensor, sensor: str = "") -> None:
        self.images = images_N3HW
        self.sensor = sensor

    def __len__(self) -> int:
        return len(self.images)

    def __getitem__(self, index: int) -> dict[str, Any]:
        return {"tactile": self.images[index], "label": -1, "text": "", "sensor": self.sensor, "id": str(index)}


def contact_fraction(images_N3HW: torch.Tensor) -> torch.Tensor:
    """(N,) fraction of each image's pixels in contact (:func:`~vqtouch.plugins.evaluation.contact.contact_mask`
    with the floor :data:`CONTACT_PIXEL_THRESHOLD`) against the no-contact background: the
    per-pixel median of the other images (contacts move around, the background stays; leaving the
    image out keeps its noise out of its background, so the noise estimate is not too low)."""
    from vqtouch.plugins.evaluation.contact import contact_mask, median_background

    if len(images_N3HW) < 2:
        raise ValueError("the contact fraction needs at least 2 images (the others make the background)")
    fractions = []
    for index in range(len(images_N3HW)):
        others = torch.cat([images_N3HW[:index], images_N3HW[index + 1 :]])
        background = median_background(others)[None]
        fractions.append(
            contact_mask(images_N3HW[index : index + 1], background, CONTACT_PIXEL_THRESHOLD).double().mean()
        )
    return torch.stack(fractions)


def check_contacts(images_N3HW: torch.Tensor, name: str) -> None:
    """Refuse a set of frames in which nothing touches the gel (only no-contact frames)."""
    if len(images_N3HW) < 2:
        return
    fraction = contact_fraction(images_N3HW[:MAX_CONTACT_CHECK_IMAGES])
    if float(fraction.max()) < MIN_CONTACT_FRACTION:
        raise AdaptationRefused(
            f"{name}: the {len(images_N3HW)} images look like no-contact frames (no image differs from the "
            f"others' background on more than {float(fraction.max()):.2%} of its pixels); adaptation needs frames "
            "of objects pressed into the gel"
        )


def target_images(
    spec: str, host: PluginHost, *, shots: int, eval_images: int, image_size: ImageSize, seed: int
) -> tuple[str, str, torch.Tensor, torch.Tensor]:
    """(name, source, shots, held-out images) of the unseen sensor ``spec``.

    A folder's images are shuffled with ``seed``; the first ``shots`` are the shots and the last
    ``eval_images`` (at most all the others) are held out, so runs with fewer shots score the
    same held-out images (a folder must keep at least one).  A registered sensor renders the shots
    and, from other scenes, ``eval_images`` held-out images.
    """
    path = folder_of(spec)
    if path is not None:
        files = sensor_folder_files(path, host)
        if len(files) < 2:
            raise DatasetError(
                f"{path}: {len(files)} image(s); adaptation needs the shots plus at least one "
                "held-out image to score it"
            )
        if shots >= len(files):
            raise ConfigError(
                f"--shots {shots}: the folder {path} holds {len(files)} images; use at most "
                f"{len(files) - 1} shots (the rest are held out to score the adaptation)"
            )
        order = torch.randperm(len(files), generator=torch.Generator().manual_seed(seed)).tolist()
        held_out = min(eval_images, len(files) - shots)
        chosen = [files[i] for i in order[:shots] + order[len(files) - held_out :]]
        sensor = sensor_images(str(path), host, count=len(chosen), image_size=image_size, files=chosen)
        return sensor.name, sensor.source, sensor.images[:shots], sensor.images[shots:]
    trained = sensor_images(spec, host, count=shots, image_size=image_size, seed=seed + 101)
    held_out = sensor_images(spec, host, count=eval_images, image_size=image_size, seed=seed + 202)
    return trained.name, trained.source, trained.images, held_out.images


def family_images(
    families: SensorFamilies,
    family: int,
    host: PluginHost,
    *,
    count: int,
    image_size: ImageSize,
    seed: int,
    exclude: str = "",
) -> tuple[torch.Tensor, list[str]]:
    """``count`` images of ``family``'s members (but the sensor whose source is ``exclude``), drawn
    evenly from every member: rendered scenes (new seeds) or a folder's images (repeated when it
    holds fewer).  Returns the images and the members used."""
    members = [member for member in families.members(family) if member["source"] != exclude]
    if not members:
        raise AdaptationRefused(
            f"family {family} has no member other than the unseen sensor itself: no family data to mix with the shots"
        )
    per_member = [count // len(members) + (index < count % len(members)) for index in range(len(members))]
    chunks = []
    for index, (member, wanted) in enumerate(zip(members, per_member)):
        if wanted == 0:
            continue
        images = sensor_images(
            member["source"], host, count=wanted, image_size=image_size, seed=seed + 1009 * (index + 1)
        ).images
        chunks.append(images.repeat(math.ceil(wanted / len(images)), 1, 1, 1)[:wanted])
    return torch.cat(chunks), [member["name"] for member in members]


def rebase_image(
    families: SensorFamilies,
    family: int,
    host: PluginHost,
    sensor_background_3HW: torch.Tensor,
    family_N3HW: torch.Tensor,
    family_background_3HW: torch.Tensor | None,
    settings: AdaptSettings,
) -> torch.Tensor:
    """The family's no-contact image minus the sensor's (:attr:`AdaptSettings.rebase`).  The family's is
    ``family_background_3HW`` when given, else the per-pixel median of its images drawn for the mix
    (64 drawn when the mix holds fewer, as at ratio 0)."""
    if family_background_3HW is None:
        if len(family_N3HW) < MIN_BACKGROUND_IMAGES:
            family_N3HW, _ = family_images(
                families,
                family,
                host,
                count=64,
                image_size=families.summary["image_size"],
                seed=settings.seed + 31_337,
            )
        family_background_3HW = median_background(family_N3HW)
    return family_background_3HW.float() - sensor_background_3HW.float()


def sensor_background(target: str, host: PluginHost, image_size: ImageSize) -> tuple[torch.Tensor, str]:
    """The unseen sensor's no-contact image (3, H, W) and how it was made: a registered sensor (name
    or JSON variant) rendering no contact; for a folder, which holds no such frame, the per-pixel
    median of its images (at most :data:`MAX_BACKGROUND_IMAGES`, evenly spaced: contacts move
    around, the background stays; :func:`~vqtouch.plugins.evaluation.contact.median_background`, the
    estimate every stage makes of captured frames)."""
    path = folder_of(target)
    if path is None:
        source = sensor_images(target, host, count=1, image_size=image_size).source  # checks the spec too
        sensor = host.build("sensor_family", json.loads(source))
        background = no_contact_image(sensor, torch.zeros(1, 3, *image_hw(image_size)))[0]
        return background, RENDERED_BACKGROUND
    files = sensor_folder_files(path, host)
    chosen = [files[index] for index in evenly_spaced(len(files), MAX_BACKGROUND_IMAGES)]
    images = sensor_images(str(path), host, count=len(chosen), image_size=image_size, files=chosen).images
    return median_background(images), (
        f"the per-pixel median of {len(chosen)} of the folder's {len(files)} "
        "images (the folder holds no no-contact frame)"
    )


def real_frames(target: str, host: PluginHost, image_size: ImageSize) -> torch.Tensor | None:
    """The captured frames of ``target`` when it is a registered sensor family (no variant: a
    variant's perturbations are not in the family's frames) that ships some."""
    if folder_of(target) is not None:
        return None
    text = target.strip()
    config = host.validate("sensor_family", json.loads(text) if text.startswith("{") else {"name": text})
    variant = getattr(config, "variant", None)
    if variant is not None and not variant.is_identity():
        return None
    return host.build("sensor_family", config).reference_frames(*image_hw(image_size))

"""Few-shot adaptation of a family tokenizer to an unseen sensor: what ``vqtouch adapt`` does.

1. The unseen sensor's images are split into the *shots* (the few images adaptation may train
   on, a seeded draw) and held-out images (the rest of a folder, or other scenes rendered by a
   registered sensor) that score the tokenizer before and after.
2. Its prototype (from the shots, computed as the families' members' were) is assigned to the
   nearest family, or refused beyond the threshold (:mod:`.families`): no silent wrong assignment.
3. The mixed set is the shots plus ``ratio`` times as many images of the family's members
   (the paper's 1:5 mix), drawn evenly from every member.
4. The family tokenizer is fine-tuned on the mixed set with its own objective (the run's
   ``tokenizer.loss``; the adversarial term only when the run's discriminator was saved) and
   written as its own checkpoint folder, whose headers name the family, its members and the shots.
   Held-out images of the family are scored before and after too: what the adaptation keeps of
   the family (the mix's purpose) or forgets.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

import torch

from vqtouch.plugins.runtime.outputs import output_folder
from vqtouch.core import ConfigError, DatasetError, PluginHost, VqtouchError
from vqtouch.plugins.utils.files import FileModel
from vqtouch.core.image_size import ImageSize, image_hw, size_text
from vqtouch.plugins.evaluation.contact import (
    MAX_BACKGROUND_IMAGES,
    RENDERED_BACKGROUND,
    evenly_spaced,
    median_background,
    no_contact_image,
)
from vqtouch.plugins.tokenizer import TOKENIZER_FILES, tokenizer_digest

from vqtouch.plugins.data.sensor_folders import folder_of, sensor_folder_files

from .families import SensorFamilies, save_families, sensor_images
from .stages_plugin import AdaptSettings  # light, for the stage section and the commands' defaults

#: Fewer family images than this give a rebase no reliable median background: 64 more are drawn.
MIN_BACKGROUND_IMAGES = 32

#: What an adaptation writes into its output folder besides the tokenizer files (the families
#: only when it fitted them itself).
ADAPT_JSON, BEFORE_AFTER_PNG, FAMILIES_FOLDER = "adapt.json", "before_after.png", "families"
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


def reconstruction_scores(
    tokenizer: Any,
    images_N3HW: torch.Tensor,
    host: PluginHost,
    batch_size: int = 32,
    metrics: tuple[str, ...] = ("ssim", "psnr"),
    background_3HW: torch.Tensor | None = None,
) -> dict[str, Any]:
    """The ``metrics`` (plugin names), codebook usage and codes used of ``tokenizer`` reconstructing
    ``images_N3HW`` (on the tokenizer's device).

    Given the sensor's no-contact image ``background_3HW``, also that image's scores against the
    same images (``background_<metric>``: what a tokenizer that draws only the background gets)
    and both on the contact region (``contact_*``, ``background_contact_*``, ``contact_fraction``;
    :func:`~vqtouch.plugins.tokenizer.evaluate_reconstruction`).
    """
    from vqtouch.plugins.tokenizer import evaluate_reconstruction

    built = {name: host.build("metric", {"name": name}) for name in metrics}
    scores = evaluate_reconstruction(
        tokenizer,
        ImageSet(images_N3HW),
        built,
        batch_size=batch_size,
        device=tokenizer.device,
        background_3HW=background_3HW,
    )
    kept = (*metrics, "codebook_usage", "codes_used", "samples", "skipped")
    # The background and contact-region entries exist only when a background was given.
    compared = ("background_", "contact_")
    return {
        key: (round(value, 4) if isinstance(value, float) else value)
        for key, value in scores.items()
        if key in kept or key.startswith(compared)
    }


def choose_family(
    families: SensorFamilies,
    tokenizer: Any,
    name: str,
    source: str,
    shots_N3HW: torch.Tensor,
    settings: AdaptSettings,
    host: PluginHost,
    out: Path,
    report: Any,
) -> tuple[dict[str, Any], int]:
    """The sensor's assignment and the family it adapts from (``settings.family`` when given); families
    fitted for this adaptation are written into ``out`` with the sensor.  Raises
    :class:`AdaptationRefused` when the sensor matches no family and none is named."""
    assignment, shown = families.unseen(tokenizer, name, shots_N3HW, settings.threshold)
    if families.features is not None:  # fitted for this adaptation (not read back): write them, with the sensor
        save_families(
            families, out / FAMILIES_FOLDER, host, {"assignments": {name: {"source": source, **assignment}}}, [shown]
        )
    family = assignment["family"]
    if settings.family is not None:
        if not 0 <= settings.family < len(families.summary["families"]):
            raise ConfigError(
                f"--family {settings.family}: the families are numbered 0 to {len(families.summary['families']) - 1}"
            )
        family = settings.family
    elif assignment["refused"]:
        nearest = assignment["nearest_family"]
        raise AdaptationRefused(
            f"{name} matches no sensor family: {assignment['distances'][nearest]:.4g} from the nearest (family "
            f"{nearest}: {', '.join(families.summary['families'][nearest])}), beyond the threshold "
            f"{assignment['threshold']:.4g}; cluster it with more sensors, raise --threshold, or name a family with "
            "--family"
        )
    report(
        f"{name}: family {family} ({', '.join(families.summary['families'][family])}); distances "
        f"{assignment['distances']}, margin {assignment['margin']:.4g}"
    )
    return assignment, family


def write_adapted(
    out: Path,
    tokenizer: Any,
    summary: dict[str, Any],
    header: dict[str, str],
    host: PluginHost,
    step_reached: int,
    rebase_3HW: torch.Tensor | None,
    pictures_N3HW: torch.Tensor,
) -> None:
    """The adapted tokenizer's files (and its rebase image), ``before_after.png`` (held-out images over
    their reconstructions before and after: ``pictures_N3HW``, three rows) and ``adapt.json``."""
    from vqtouch.core import atomic_write, save
    from vqtouch.plugins.utils.images import image_grid, save_png
    from vqtouch.plugins.tokenizer import TOKENIZER_FILES, save_rebase

    output_folder(out)
    for file, module in zip(TOKENIZER_FILES, (tokenizer.autoencoder, tokenizer.quantizer)):
        save(module, out / file, step=step_reached, host=host, metadata=header)
    if rebase_3HW is not None:
        save_rebase(out, rebase_3HW, header)
    save_png(image_grid(pictures_N3HW, columns=len(pictures_N3HW) // 3), out / BEFORE_AFTER_PNG)
    atomic_write(out / ADAPT_JSON, lambda tmp: tmp.write_text(json.dumps(summary, indent=2) + "\n"))


def adapt_tokenizer(
    run_or_folder: Any,
    target: str,
    families: SensorFamilies,
    host: PluginHost,
    out: Path,
    settings: AdaptSettings,
    *,
    step: int | str | None = None,
    overwrite: bool = False,
    report: Any = print,
    background_3HW: torch.Tensor | None = None,
    family_background_3HW: torch.Tensor | None = None,
) -> dict[str, Any]:
    """Adapt the tokenizer of ``run_or_folder`` to the unseen sensor ``target`` (see the module
    docstring); writes the adapted tokenizer, ``adapt.json`` and ``before_after.png`` into ``out``
    and returns the summary.  Raises :class:`AdaptationRefused` when the sensor matches no family
    (unless ``settings.family`` names one) or its images hold no contact.  Given the sensor's
    no-contact image ``background_3HW`` (by default :func:`sensor_background`), the held-out scores
    before and after carry the background's and the contact region's (:func:`reconstruction_scores`).
    With ``settings.rebase``, ``family_background_3HW`` is the family's no-contact image the sensor's
    images are moved onto (default: the per-pixel median of the family images drawn for it)."""
    from vqtouch.plugins.utils.seeding import resolve_device
    from vqtouch.plugins.training.trainer import Trainer
    from vqtouch.plugins.tokenizer import load_tokenizer, reconstruct_all, tokenizer_task
    from vqtouch.plugins.tokenizer import TokenizerLossConfig, TokenizerTrainConfig, disc_start_step

    refuse_existing(out, overwrite)
    if settings.part not in ADAPTED_PARTS:
        raise ConfigError(f"--part {settings.part!r}: choose {' or '.join(ADAPTED_PARTS)}")
    if settings.shots < 1 or settings.ratio < 0:
        raise ConfigError(f"shots must be >= 1 and ratio >= 0 (got {settings.shots}, {settings.ratio})")
    tokenizer, folder = load_tokenizer(run_or_folder, host, step=step)
    run_config = _run_config(folder, host)
    device = resolve_device(run_config.device if run_config is not None else "auto")
    tokenizer.to(device)
    image_size = families.summary["image_size"]
    if image_hw(tokenizer.autoencoder.vqtouch_spec.context.image_size) != image_hw(image_size):
        raise ConfigError(
            f"the families were fitted at {size_text(image_size)} px, the tokenizer works at "
            f"{size_text(tokenizer.autoencoder.vqtouch_spec.context.image_size)} px: cluster with "
            "this tokenizer"
        )
    section = run_config.tokenizer if run_config is not None else None
    loss = section.loss if section is not None else TokenizerLossConfig()
    train = (section.train if section is not None else TokenizerTrainConfig()).model_copy(
        update={
            "steps": settings.steps,
            "checkpoint_every": max(1, settings.steps),
            "keep_best": False,
            **({"learning_rate": settings.learning_rate} if settings.learning_rate is not None else {}),
        }
    )
    batch_size = settings.batch_size or (run_config.data.batch_size if run_config is not None else 16)

    name, source, shots_N, held_out_M = target_images(
        target, host, shots=settings.shots, eval_images=settings.eval_images, image_size=image_size, seed=settings.seed
    )
    check_contacts(torch.cat([shots_N, held_out_M]), name)
    assignment, family = choose_family(families, tokenizer, name, source, shots_N, settings, host, out, report)
    family_count = round(settings.shots * settings.ratio)
    if settings.family is not None and family != assignment["family"] and settings.ratio > 1:
        # Measured on a low-contrast sensor (docs/results.md): another family's images at 1:5 washed
        # its contact out (+0.4 dB over the no-contact image), at 1:1 it was kept (+2.7 dB).
        report(
            f"note: family {family} is not the one {name} is nearest to (family {assignment['family']}); "
            f"mixed 1:{settings.ratio:g}, its images can wash out a faint sensor's contact; --ratio 1 or 0 keeps it"
        )
    members: list[str] = []
    family_N = torch.zeros(0, *shots_N.shape[1:])
    if family_count > 0:
        family_N, members = family_images(
            families, family, host, count=family_count, image_size=image_size, seed=settings.seed, exclude=source
        )
    background_source = "given by the caller"
    if background_3HW is None:
        background_3HW, background_source = sensor_background(target, host, image_size)
    rebase_3HW = None
    if settings.rebase:
        rebase_3HW = rebase_image(families, family, host, background_3HW, family_N, family_background_3HW, settings)
    # Rebased, the sensor's images train as the family's no-contact image plus their own contact.
    shots_in = shots_N if rebase_3HW is None else shots_N + rebase_3HW
    mixed_set = ImageSet(torch.cat([shots_in, family_N]), name)
    if len(mixed_set) < batch_size:
        batch_size = len(mixed_set)  # a handful of shots still trains (one batch = every image)
    before = reconstruction_scores(tokenizer, held_out_M, host, batch_size, settings.metrics, background_3HW)
    # Held-out family images (new scenes): what the adaptation keeps of the family, or forgets.
    family_held_out, _ = family_images(
        families,
        family,
        host,
        count=settings.eval_images,
        image_size=image_size,
        seed=settings.seed + 77_777,
        exclude=source,
    )
    family_before = reconstruction_scores(tokenizer, family_held_out, host, batch_size)
    before_images = reconstruct_all(tokenizer, held_out_M[:8].to(device)).cpu()
    real = _real_frames(target, host, image_size)  # the sensor's own captured frames, when it ships some (taxim)
    real_before = (
        reconstruction_scores(tokenizer, real, host, batch_size, settings.metrics) if real is not None else None
    )
    discriminator, adversarial = _discriminator(folder, loss, host)
    if discriminator is not None:
        # disc_start counts in the family run's steps: the adaptation continues that run's schedule.
        trained = getattr(tokenizer.autoencoder, "vqtouch_step", 0)
        run_steps = (section.train if section is not None else TokenizerTrainConfig()).steps
        loss = loss.model_copy(update={"disc_start": max(0, disc_start_step(loss.disc_start, run_steps) - trained)})
    if settings.part == "decoder":
        freeze_all_but_the_decoder(tokenizer)
    task = tokenizer_task(tokenizer, loss, device, discriminator)
    trainer = Trainer(
        task,
        mixed_set,
        train,
        batch_size=batch_size,
        seed=settings.seed,
        device=device,
        checkpoint_dir=None,
        host=host,
        stage="adapt",
    )
    tic = time.perf_counter()
    trainer.fit()
    seconds = time.perf_counter() - tic
    tokenizer.eval()
    # The family's images are scored as they are: the rebase moves the new sensor's images only.
    family_after = reconstruction_scores(tokenizer, family_held_out, host, batch_size)
    tokenizer.rebase_3HW = None if rebase_3HW is None else rebase_3HW.to(device)
    after = reconstruction_scores(tokenizer, held_out_M, host, batch_size, settings.metrics, background_3HW)
    after_images = reconstruct_all(tokenizer, held_out_M[:8].to(device)).cpu()

    summary: dict[str, Any] = {
        "target": name,
        "target_source": source,
        "adapted_from": str(folder),
        "family": family,
        "family_members": families.summary["families"][family],
        "members_used": members,
        "assignment": assignment,
        "forced_family": settings.family is not None,
        "seed": settings.seed,
        "shots": len(shots_N),
        "ratio": settings.ratio,
        "family_images": family_count,
        "held_out": len(held_out_M),
        "steps": settings.steps,
        "part": settings.part,
        "rebase": settings.rebase,
        "learning_rate": train.learning_rate,
        "batch_size": batch_size,
        "adversarial": adversarial,
        "seconds": round(seconds, 2),
        "background": background_source,
        "before": before,
        "after": after,
        "family_held_out": {"images": len(family_held_out), "before": family_before, "after": family_after},
    }
    if real is not None:
        summary["real_frames"] = {
            "count": len(real),
            "before": real_before,
            "after": reconstruction_scores(tokenizer, real, host, batch_size, settings.metrics),
        }
    header = {
        "adaptation.target": source,
        "adaptation.family": str(family),
        "adaptation.family_members": json.dumps(summary["family_members"]),
        "adaptation.shots": str(len(shots_N)),
        "adaptation.ratio": f"{settings.ratio:g}",
        "adaptation.adapted_from": str(folder),
        "adaptation.part": settings.part,
    }
    step_reached = getattr(tokenizer.autoencoder, "vqtouch_step", 0) + settings.steps
    count = len(before_images)
    pictures = torch.cat([held_out_M[:count], before_images, after_images])
    write_adapted(out, tokenizer, summary, header, host, step_reached, rebase_3HW, pictures)
    return summary


class AdaptRecord(FileModel):
    """What is read back of an ``adapt.json``: the tokenizer adapted from and the settings."""

    target: str
    adapted_from: str
    family: int
    seed: int
    shots: int
    ratio: float
    held_out: int
    steps: int
    part: str = "all"
    rebase: bool = False


#: What adaptation can fine-tune (:attr:`AdaptSettings.part`).
ADAPTED_PARTS = ("all", "decoder")


def freeze_all_but_the_decoder(tokenizer: Any) -> None:
    """Let only the decoder's parameters train: the codebook and the encoder keep every image's codes."""
    if tokenizer.quantizer.vqtouch_spec.config.name == "ema_vq":
        raise ConfigError(
            "decoder-only adaptation keeps the codebook, but an ema_vq quantizer moves it while training; "
            "adapt the whole tokenizer (--part all)"
        )
    decoder = {id(param) for param in tokenizer.decoder_parameters()}
    for param in tokenizer.autoencoder.parameters():
        param.requires_grad_(id(param) in decoder)
    for param in tokenizer.quantizer.parameters():
        param.requires_grad_(False)


def refuse_existing(out: Path, overwrite: bool) -> None:
    """Refuse to replace an adapted tokenizer already in ``out`` unless ``overwrite``."""
    if (out / "autoencoder.safetensors").exists() and not overwrite:
        raise ConfigError(f"{out} already holds an adapted tokenizer; choose another --out or pass --overwrite")


def _run_config(folder: Path, host: PluginHost) -> Any:
    """The config of the run a checkpoint folder belongs to, or None for a loose folder."""
    from vqtouch.plugins.runtime.run_dir import RunDir

    run_path = folder.parent.parent
    if folder.parent.name == "checkpoints" and (run_path / "config.json").is_file():
        return RunDir.open(run_path).load_config(host)
    return None


def _discriminator(folder: Path, loss: Any, host: PluginHost) -> tuple[Any, str]:
    """The run's discriminator when its objective is adversarial and it was saved, and why not otherwise."""
    from vqtouch.core import load

    if loss.adversarial_weight == 0:
        return None, "off (tokenizer.loss.adversarial_weight = 0)"
    path = folder / "discriminator.safetensors"
    if not path.is_file():
        return None, f"off (no {path.name} beside the tokenizer: it trained without one)"
    return load(path, host=host), "on (the run's discriminator, fine-tuned too)"


def _real_frames(target: str, host: PluginHost, image_size: ImageSize) -> torch.Tensor | None:
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


def default_families(
    tokenizer: Any,
    host: PluginHost,
    *,
    image_size: ImageSize,
    tokenizer_source: str,
    exclude: str = "",
    clusterer: dict[str, Any] | None = None,
    variants_per_family: int = 3,
    images: int = 32,
    seed: int = 0,
    report: Any = print,
) -> SensorFamilies:
    """Families of every registered sensor family and ``variants_per_family`` environmental
    variants of each (:func:`.families.family_sensor_specs`), clustered with ``clusterer``
    (default: k-means, the family count by silhouette); the sensor whose source is ``exclude``
    (the unseen one) is left out."""
    from .families import family_sensor_specs, fit_families

    specs = [spec for spec in family_sensor_specs(host, variants_per_family) if spec != exclude]
    return fit_families(
        tokenizer,
        specs,
        host,
        clusterer=host.build("clusterer", clusterer or {"name": "kmeans"}),
        images=images,
        image_size=image_size,
        seed=seed,
        tokenizer_source=tokenizer_source,
        report=report,
    )


def families_to_adapt_from(
    tokenizer: Any, folder: Path, host: PluginHost, *, families: Path | None, where: str, exclude: str, seed: int
) -> SensorFamilies:
    """The families an adaptation assigns its target to: those saved in ``families`` (``where`` names
    them in the refusal when they were fitted on another tokenizer than the one in ``folder``), else the
    registered defaults, clustered now with ``tokenizer`` (:func:`default_families`)."""
    from .families import load_families

    if families is not None:
        loaded = load_families(families, host)
        check_same_tokenizer(loaded, folder, where)
        return loaded
    return default_families(
        tokenizer,
        host,
        image_size=tokenizer.autoencoder.vqtouch_spec.context.image_size,
        tokenizer_source=str(folder),
        exclude=exclude,
        seed=seed,
        report=lambda line: None,
    )


def check_same_tokenizer(families: SensorFamilies, tokenizer_folder: Path, where: str) -> None:
    """Refuse families fitted on another tokenizer's features: distances to them mean nothing."""
    fitted = families.summary.get("tokenizer", "")
    digest = families.summary.get("tokenizer_sha256")
    if digest and all((tokenizer_folder / name).is_file() for name in TOKENIZER_FILES):
        same = tokenizer_digest(tokenizer_folder) == digest
    else:  # families written before digests were recorded
        same = not fitted or Path(fitted).resolve() == tokenizer_folder.resolve()
    if not same:
        raise ConfigError(
            f"{where} were fitted on the features of {fitted}, not of {tokenizer_folder} (the tokenizer "
            "being adapted); run `vqtouch cluster` with this tokenizer, or adapt that one"
        )

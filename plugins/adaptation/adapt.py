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
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from vqtouch.plugins.runtime.outputs import output_folder
from vqtouch.core import ConfigError, PluginHost
from vqtouch.plugins.utils.files import FileModel
from vqtouch.core.image_size import ImageSize, image_hw, size_text

from .adapt_images import (
    ImageSet,
    check_contacts,
    family_images,
    real_frames,
    rebase_image,
    sensor_background,
    target_images,
)
from .adapt_families import choose_family
from .families import SensorFamilies
from .stages_plugin import AdaptSettings  # light, for the stage section and the commands' defaults

#: What an adaptation writes into its output folder besides the tokenizer files (and the families,
#: :data:`~.adapt_families.FAMILIES_FOLDER`, only when it fitted them itself).
ADAPT_JSON, BEFORE_AFTER_PNG = "adapt.json", "before_after.png"


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


@dataclass
class _Mix:
    """The unseen sensor's images, the family it adapts from and the mixed set it fine-tunes on."""

    name: str
    source: str
    shots_N3HW: torch.Tensor
    held_out_M3HW: torch.Tensor
    assignment: dict[str, Any]
    family: int
    family_count: int
    members: list[str]
    background_3HW: torch.Tensor
    background_source: str
    rebase_3HW: torch.Tensor | None
    mixed_set: ImageSet


@dataclass
class _Scores:
    """The held-out images scored before and after the fine-tuning, and their scores."""

    before: dict[str, Any]
    family_N3HW: torch.Tensor
    family_before: dict[str, Any]
    before_images: torch.Tensor
    real_N3HW: torch.Tensor | None
    real_before: dict[str, Any] | None
    after: dict[str, Any] = field(default_factory=dict)
    family_after: dict[str, Any] = field(default_factory=dict)
    after_images: torch.Tensor | None = None
    real_after: dict[str, Any] | None = None


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
    refuse_existing(out, overwrite)
    _check_settings(settings)
    tokenizer, folder, run_config, device = _load_tokenizer_to_adapt(run_or_folder, host, step, families)
    image_size = families.summary["image_size"]
    loss, train, batch_size = _training_config(run_config, settings)
    mix = _draw_mix(
        target,
        families,
        tokenizer,
        host,
        settings,
        out=out,
        report=report,
        image_size=image_size,
        background_3HW=background_3HW,
        family_background_3HW=family_background_3HW,
    )
    batch_size = min(batch_size, len(mix.mixed_set))  # a handful of shots still trains (one batch = every image)
    scores = _score_before(tokenizer, mix, families, target, host, settings, image_size, batch_size, device)
    adversarial, seconds = _fine_tune(
        tokenizer, mix.mixed_set, folder, run_config, loss, train, host, settings, batch_size, device
    )
    _score_after(tokenizer, mix, scores, host, settings, batch_size, device)
    summary = _summary(mix, scores, families, folder, settings, train.learning_rate, batch_size, adversarial, seconds)
    step_reached = getattr(tokenizer.autoencoder, "vqtouch_step", 0) + settings.steps
    count = len(scores.before_images)
    pictures = torch.cat([mix.held_out_M3HW[:count], scores.before_images, scores.after_images])
    header = _header(mix, summary, folder, settings)
    write_adapted(out, tokenizer, summary, header, host, step_reached, mix.rebase_3HW, pictures)
    return summary


def _check_settings(settings: AdaptSettings) -> None:
    """Refuse a part adaptation cannot fine-tune, fewer than one shot or a negative ratio."""
    if settings.part not in ADAPTED_PARTS:
        raise ConfigError(f"--part {settings.part!r}: choose {' or '.join(ADAPTED_PARTS)}")
    if settings.shots < 1 or settings.ratio < 0:
        raise ConfigError(f"shots must be >= 1 and ratio >= 0 (got {settings.shots}, {settings.ratio})")


def _load_tokenizer_to_adapt(
    run_or_folder: Any, host: PluginHost, step: int | str | None, families: SensorFamilies
) -> tuple[Any, Path, Any, Any]:
    """The tokenizer (moved to its run's device), its folder, its run's config and the device; refuses a
    tokenizer that works at another image size than the families were fitted at."""
    from vqtouch.plugins.utils.seeding import resolve_device
    from vqtouch.plugins.tokenizer import load_tokenizer

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
    return tokenizer, folder, run_config, device


def _training_config(run_config: Any, settings: AdaptSettings) -> tuple[Any, Any, int]:
    """The fine-tuning's objective, training settings and batch size: the run's, with the adaptation's steps."""
    from vqtouch.plugins.tokenizer import TokenizerLossConfig, TokenizerTrainConfig

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
    return loss, train, batch_size


def _draw_mix(
    target: str,
    families: SensorFamilies,
    tokenizer: Any,
    host: PluginHost,
    settings: AdaptSettings,
    *,
    out: Path,
    report: Any,
    image_size: ImageSize,
    background_3HW: torch.Tensor | None,
    family_background_3HW: torch.Tensor | None,
) -> _Mix:
    """The sensor's shots and held-out images, the family it adapts from, its background and the mixed set."""
    name, source, shots_N, held_out_M = target_images(
        target, host, shots=settings.shots, eval_images=settings.eval_images, image_size=image_size, seed=settings.seed
    )
    check_contacts(torch.cat([shots_N, held_out_M]), name)
    assignment, family = choose_family(families, tokenizer, name, source, shots_N, settings, host, out, report)
    family_count = round(settings.shots * settings.ratio)
    _note_forced_family(name, assignment, family, settings, report)
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
    return _Mix(
        name=name,
        source=source,
        shots_N3HW=shots_N,
        held_out_M3HW=held_out_M,
        assignment=assignment,
        family=family,
        family_count=family_count,
        members=members,
        background_3HW=background_3HW,
        background_source=background_source,
        rebase_3HW=rebase_3HW,
        mixed_set=ImageSet(torch.cat([shots_in, family_N]), name),
    )


def _note_forced_family(
    name: str, assignment: dict[str, Any], family: int, settings: AdaptSettings, report: Any
) -> None:
    """Warn when a named family other than the nearest is mixed in at more than 1:1."""
    if settings.family is not None and family != assignment["family"] and settings.ratio > 1:
        # Measured on a low-contrast sensor (docs/results.md): another family's images at 1:5 washed
        # its contact out (+0.4 dB over the no-contact image), at 1:1 it was kept (+2.7 dB).
        report(
            f"note: family {family} is not the one {name} is nearest to (family {assignment['family']}); "
            f"mixed 1:{settings.ratio:g}, its images can wash out a faint sensor's contact; --ratio 1 or 0 keeps it"
        )


def _score_before(
    tokenizer: Any,
    mix: _Mix,
    families: SensorFamilies,
    target: str,
    host: PluginHost,
    settings: AdaptSettings,
    image_size: ImageSize,
    batch_size: int,
    device: Any,
) -> _Scores:
    """The family tokenizer's scores of the sensor's held-out images, new family scenes and the real frames."""
    from vqtouch.plugins.tokenizer import reconstruct_all

    held_out_M = mix.held_out_M3HW
    before = reconstruction_scores(tokenizer, held_out_M, host, batch_size, settings.metrics, mix.background_3HW)
    # Held-out family images (new scenes): what the adaptation keeps of the family, or forgets.
    family_held_out, _ = family_images(
        families,
        mix.family,
        host,
        count=settings.eval_images,
        image_size=image_size,
        seed=settings.seed + 77_777,
        exclude=mix.source,
    )
    family_before = reconstruction_scores(tokenizer, family_held_out, host, batch_size)
    before_images = reconstruct_all(tokenizer, held_out_M[:8].to(device)).cpu()
    real = real_frames(target, host, image_size)  # the sensor's own captured frames, when it ships some (taxim)
    real_before = (
        reconstruction_scores(tokenizer, real, host, batch_size, settings.metrics) if real is not None else None
    )
    return _Scores(
        before=before,
        family_N3HW=family_held_out,
        family_before=family_before,
        before_images=before_images,
        real_N3HW=real,
        real_before=real_before,
    )


def _fine_tune(
    tokenizer: Any,
    mixed_set: ImageSet,
    folder: Path,
    run_config: Any,
    loss: Any,
    train: Any,
    host: PluginHost,
    settings: AdaptSettings,
    batch_size: int,
    device: Any,
) -> tuple[str, float]:
    """Fine-tune ``tokenizer`` on the mixed set; returns whether the adversarial term was on, and why,
    and the seconds the training took."""
    from vqtouch.plugins.training.trainer import Trainer
    from vqtouch.plugins.tokenizer import TokenizerTrainConfig, disc_start_step, tokenizer_task

    discriminator, adversarial = _discriminator(folder, loss, host)
    if discriminator is not None:
        # disc_start counts in the family run's steps: the adaptation continues that run's schedule.
        trained = getattr(tokenizer.autoencoder, "vqtouch_step", 0)
        section = run_config.tokenizer if run_config is not None else None
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
    return adversarial, seconds


def _score_after(
    tokenizer: Any, mix: _Mix, scores: _Scores, host: PluginHost, settings: AdaptSettings, batch_size: int, device: Any
) -> None:
    """Add the adapted tokenizer's scores of the same held-out images to ``scores``."""
    from vqtouch.plugins.tokenizer import reconstruct_all

    # The family's images are scored as they are: the rebase moves the new sensor's images only.
    scores.family_after = reconstruction_scores(tokenizer, scores.family_N3HW, host, batch_size)
    tokenizer.rebase_3HW = None if mix.rebase_3HW is None else mix.rebase_3HW.to(device)
    held_out_M = mix.held_out_M3HW
    scores.after = reconstruction_scores(tokenizer, held_out_M, host, batch_size, settings.metrics, mix.background_3HW)
    scores.after_images = reconstruct_all(tokenizer, held_out_M[:8].to(device)).cpu()
    if scores.real_N3HW is not None:
        scores.real_after = reconstruction_scores(tokenizer, scores.real_N3HW, host, batch_size, settings.metrics)


def _summary(
    mix: _Mix,
    scores: _Scores,
    families: SensorFamilies,
    folder: Path,
    settings: AdaptSettings,
    learning_rate: float,
    batch_size: int,
    adversarial: str,
    seconds: float,
) -> dict[str, Any]:
    """What ``adapt.json`` records of the adaptation."""
    summary: dict[str, Any] = {
        "target": mix.name,
        "target_source": mix.source,
        "adapted_from": str(folder),
        "family": mix.family,
        "family_members": families.summary["families"][mix.family],
        "members_used": mix.members,
        "assignment": mix.assignment,
        "forced_family": settings.family is not None,
        "seed": settings.seed,
        "shots": len(mix.shots_N3HW),
        "ratio": settings.ratio,
        "family_images": mix.family_count,
        "held_out": len(mix.held_out_M3HW),
        "steps": settings.steps,
        "part": settings.part,
        "rebase": settings.rebase,
        "learning_rate": learning_rate,
        "batch_size": batch_size,
        "adversarial": adversarial,
        "seconds": round(seconds, 2),
        "background": mix.background_source,
        "before": scores.before,
        "after": scores.after,
        "family_held_out": {
            "images": len(scores.family_N3HW),
            "before": scores.family_before,
            "after": scores.family_after,
        },
    }
    if scores.real_N3HW is not None:
        summary["real_frames"] = {
            "count": len(scores.real_N3HW),
            "before": scores.real_before,
            "after": scores.real_after,
        }
    return summary


def _header(mix: _Mix, summary: dict[str, Any], folder: Path, settings: AdaptSettings) -> dict[str, str]:
    """The metadata the adapted tokenizer's files carry: the sensor, the family and the shots."""
    return {
        "adaptation.target": mix.source,
        "adaptation.family": str(mix.family),
        "adaptation.family_members": json.dumps(summary["family_members"]),
        "adaptation.shots": str(len(mix.shots_N3HW)),
        "adaptation.ratio": f"{settings.ratio:g}",
        "adaptation.adapted_from": str(folder),
        "adaptation.part": settings.part,
    }


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

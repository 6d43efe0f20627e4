"""The ``generator`` stage: train a generator over a trained tokenizer's codes, then generate and score.

The tokenizer comes from this run (the ``tokenizer`` stage ran before, as in the paper's scenes)
or from another run (``generator.tokenizer_run``, what ``vqtouch train generator --tokenizer RUN``
sets).  Its codes of the whole dataset are computed once and cached (:mod:`.codes`); training
runs through the one trainer (:mod:`.training`), with its checkpoints in
``checkpoints/generator/step-*`` (the tokenizer's stay in ``checkpoints/step-*``).  Afterwards
the held-out conditions are generated with the configured sampler and scored against their
ground-truth tactile images (:mod:`.scoring`; ``generation.json``; ``samples.png``: condition
images when there are, generated, ground truth).
"""

from __future__ import annotations

import time
import warnings
from pathlib import Path
from typing import Any

import torch

from vqtouch.core import StageJob, StageUnavailable
from vqtouch.plugins.utils.seeding import resolve_device
from vqtouch.plugins.runtime.run_dir import MissingCheckpointError, RunDir
from vqtouch.plugins.utils.splits import DatasetSubset, experiment_split
from vqtouch.core.errors import VqtouchWarning
from vqtouch.core.image_size import image_hw
from vqtouch.plugins.training.trainer import Trainer
from vqtouch.plugins.training.checkpoints import apply_ema_weights, step_folders
from vqtouch.plugins.evaluation.contact import VERDICT_EVIDENCE, dataset_background
from vqtouch.plugins.evaluation.directions import shown_scores

from .scoring import baseline_pool, distribution_scorer, held_out_conditions, sampling_precision, score_generation
from .stage_plugin import GeneratorSection  # noqa: F401 - re-exported
from .training import CodesDataset, GeneratorTask
from vqtouch.plugins.tokenizer import (
    tokenizer_paths,
    load_tokenizer,
    tokenizer_digest,
    tokenizer_location,
)


class ConditionIsTargetWarning(VqtouchWarning):
    """A conditioner reads the very image the generator learns to produce."""


#: Where a run keeps the generator's checkpoints, below its checkpoints/ folder.
CHECKPOINT_FOLDER = "generator"


def tokenizer_source(job: StageJob) -> RunDir | Path:
    """Where the tokenizer is: ``generator.tokenizer_run`` (a run, a tokenizer checkpoint folder or a
    bundle, ``pretrained:NAME``), else this run."""

    path = job.section.tokenizer_run
    return tokenizer_location(path, job.host) if path else job.run


def load_run_tokenizer(job: StageJob, device: torch.device) -> tuple[Any, Path]:
    """The trained tokenizer the generator works with, and its checkpoint folder."""

    source = tokenizer_source(job)
    try:
        tokenizer, folder = load_tokenizer(source, job.host, device=str(device))
    except MissingCheckpointError as exc:
        where = "this run" if source is job.run else str(getattr(source, "path", source))
        raise StageUnavailable(
            f"no trained tokenizer in {where} ({exc}); run the tokenizer stage first or give --tokenizer RUN"
        ) from None
    return tokenizer, folder


def images_config(config: Any) -> dict[str, Any]:
    """What decides the dataset's images (and so its codes): the code cache's key."""
    data = config.to_dict()
    return {
        "dataset": data["data"]["dataset"],
        "image_size": data["data"]["image_size"],
        "sensor": data.get("sensor"),
        "target_sensor": data.get("target_sensor"),
    }


def check_condition_keys(config: Any, host: Any, conditioners: Any = None) -> None:
    """Refuse, in one line before anything is written or trained, a generator whose conditioners read
    sample entries (:meth:`~vqtouch.core.Conditioner.sample_entries`) the config's dataset does not
    provide, naming the conditioner, its distribution and the missing key.  Builds the dataset (and the
    conditioners, unless given already built) and reads one sample."""
    from vqtouch.core import Assembly, ConfigError

    section = getattr(config, "generator", None)
    if section is None or not section.conditioners or config.data.dataset is None:
        return
    assembly = Assembly(config, host)
    dataset = assembly.component("data.dataset")
    if len(dataset) == 0:
        return
    sample = dataset[0]
    for conditioner in conditioners if conditioners is not None else assembly.component("generator.conditioners"):
        missing = [key for key in conditioner.sample_entries() if key not in sample]
        if missing:
            spec = conditioner.vqtouch_spec
            raise ConfigError(
                f"conditioner {spec.config.name!r} ({spec.source.describe()}) reads the samples' {missing[0]!r}, "
                f"which dataset {config.data.dataset.name!r} does not provide (its samples have "
                f"{', '.join(sorted(sample))}); use a dataset that provides it, or another conditioner"
            )


def train_generator(job: StageJob) -> dict[str, Any]:
    """Train the configured generator in ``job.run`` and score samples of the held-out conditions."""

    config, section, assembly = job.config, job.section, job.assembly
    if section.sensor_tag is not None:
        raise StageUnavailable(
            "generator.sensor_tag is set: a sensor-tagged generator is fine-tuned by `vqtouch fewshot` "
            "(family data and an unseen sensor's images), not by the generator stage; remove sensor_tag"
        )
    device = resolve_device(config.device)
    tokenizer, tokenizer_folder = load_run_tokenizer(job, device)
    generator = assembly.component("generator.model")
    conditioners = assembly.component("generator.conditioners")
    _check_codebook(generator, tokenizer, tokenizer_folder)
    dataset, data, cache = _training_codes(job, tokenizer, tokenizer_folder, generator, conditioners, device)
    train_set, val_set = experiment_split(data, config.data, config.seed)
    background_note, background_3HW = None, None
    wants_contact = getattr(section.model, "contact_weight", 0) > 0
    if section.train.canonical_background:
        background_note, background_3HW = canonicalise_codes(
            data, train_set, dataset, tokenizer, image_hw(config.data.image_size), contact=wants_contact
        )
    grid_note = None
    # A resumed run's checkpoint already holds the pretrained grid (and the generator trained on from it).
    resuming = job.resume and bool(step_folders(job.run.checkpoints / CHECKPOINT_FOLDER))
    if section.train.grid_pretrain.steps and not resuming:
        grid_note = grid_pretraining(
            job, generator, conditioners, tokenizer, tokenizer_folder, data, train_set, dataset, background_3HW, device
        )
    task = GeneratorTask(
        generator, conditioners, section.train.condition_dropout, config.seed, section.train.conditioner_weights
    )
    trainer = _generator_trainer(job, task, train_set, val_set, device)
    if job.resume:
        job.run.resume(trainer, job.host, stage=CHECKPOINT_FOLDER)
    state = trainer.fit()
    result: dict[str, Any] = {
        "step": state.step,
        "trained_in": trainer.precision,  # generator.train.precision with auto resolved for this machine
        "train_samples": len(train_set),
        "val_samples": len(val_set),
        "split_unit": val_set.split_unit,
        "code_cache": cache,
        "tokenizer": str(tokenizer_folder),
        "canonical_background": background_note,
    }
    if grid_note is not None:
        result["grid_pretrain"] = grid_note
    if trainer.validates():
        result |= {"best_step": state.best_step, "best_val_loss": state.best_score}
    if trainer.dist.is_main:
        _publish_generator(job, trainer, state, tokenizer_folder)
        if section.num_samples and len(val_set) and section.sampler is not None:
            result |= _score_trained(job, trainer, task, tokenizer, val_set, train_set, dataset, device)
        job.run.write_json("generation.json", result)
    return result


def _check_codebook(generator: Any, tokenizer: Any, tokenizer_folder: Path) -> None:
    """Refuse a generator built for another number of codes than the tokenizer's codebook."""
    codebook = tokenizer.quantizer.codebook_size
    if getattr(generator, "num_codes", codebook) != codebook:
        raise StageUnavailable(
            f"the generator was built for {generator.num_codes} codes but the tokenizer in "
            f"{tokenizer_folder} has {codebook}; the run's tokenizer section must match that "
            "tokenizer's config"
        )


def _training_codes(
    job: StageJob, tokenizer: Any, tokenizer_folder: Path, generator: Any, conditioners: Any, device: torch.device
) -> tuple[Any, CodesDataset, dict[str, Any]]:
    """The dataset, its codes with the conditioners' sample entries, and how the code cache served them."""
    from .codes import dataset_codes

    config, section = job.config, job.section
    dataset = job.assembly.component("data.dataset")
    codes_NHW, cache = dataset_codes(
        tokenizer,
        tokenizer_paths(tokenizer_folder),
        dataset,
        images_config(config),
        batch_size=config.data.batch_size,
        device=device,
        use_cache=section.train.code_cache,
    )
    grid = getattr(generator, "grid_hw", tuple(codes_NHW.shape[1:]))
    if tuple(codes_NHW.shape[1:]) != tuple(grid):
        raise StageUnavailable(
            f"the tokenizer makes {tuple(codes_NHW.shape[1:])} code grids but the generator was "
            f"built for {tuple(grid)}; data.image_size must be the tokenizer's"
        )
    keys = list(dict.fromkeys(key for conditioner in conditioners for key in conditioner.sample_entries()))
    if "tactile" in keys:
        # stacklevel 3: the warning names the caller of train_generator.
        warnings.warn(
            "a conditioner reads samples' 'tactile' image, which is also the image the generator learns to "
            "produce: it can learn to copy its condition; for touch-to-touch, condition on a second sensor's "
            "image of the same contact (tactile conditioner reads=tactile_source, with paired_sensor set)",
            ConditionIsTargetWarning,
            stacklevel=3,
        )
    return dataset, CodesDataset.collect(codes_NHW, dataset, keys), cache


def _generator_trainer(
    job: StageJob, task: GeneratorTask, train_set: Any, val_set: Any, device: torch.device
) -> Trainer:
    """The trainer of ``task``, its checkpoints in the run's generator folder."""
    config = job.config
    return Trainer(
        task,
        train_set,
        job.section.train,
        batch_size=config.data.batch_size,
        seed=config.seed,
        device=device,
        checkpoint_dir=job.run.checkpoints / CHECKPOINT_FOLDER,
        run=job.run,
        num_workers=0,
        host=job.host,
        stage=job.stage,
        val_dataset=val_set,
    )


def _publish_generator(job: StageJob, trainer: Trainer, state: Any, tokenizer_folder: Path) -> None:
    """Publish the trained generator's last checkpoint, pinned to the tokenizer it learned the codes of."""
    # The tokenizer is recorded by its step folder, relative to the run when it is the run's own, so
    # that readers use the codes the generator learned even after the tokenizer trains on.
    inside = tokenizer_folder.resolve().is_relative_to(job.run.path.resolve())
    recorded = tokenizer_folder.resolve().relative_to(job.run.path.resolve()) if inside else tokenizer_folder.resolve()
    digest = tokenizer_digest(tokenizer_folder)
    job.publish(
        "generator",
        trainer.last_checkpoint,
        step=state.step,
        tokenizer=recorded.as_posix(),
        tokenizer_sha256=digest,
    )


def _score_trained(
    job: StageJob,
    trainer: Trainer,
    task: GeneratorTask,
    tokenizer: Any,
    val_set: Any,
    train_set: Any,
    dataset: Any,
    device: torch.device,
) -> dict[str, Any]:
    """The scores of the trained generator's samples (:func:`score_samples`), drawn with the weights
    ``generator.sample_weights`` names."""
    result: dict[str, Any] = {}
    if trainer.ema and job.section.sample_weights == "ema":
        # Training is over and its checkpoint written: the stage's samples come from the
        # weights readers will load (load_pipeline prefers the average too).
        for name, module in task.modules.items():
            apply_ema_weights(module, trainer.ema[name], f"the {name} EMA")
        result["sample_weights"] = "ema"
    return result | score_samples(job, tokenizer, task, val_set, train_set, dataset, device)


def canonicalise_codes(
    data: CodesDataset,
    train_set: Any,
    dataset: Any,
    tokenizer: Any,
    size_hw: tuple[int, int],
    *,
    contact: bool = False,
) -> tuple[dict[str, Any], torch.Tensor | None]:
    """Replace ``data``'s codes by their canonical-background form (:func:`.codes.canonical_background`)
    in place, with the no-contact image of the training split, and with ``contact`` add each sample's
    contact cells (:data:`.training.CONTACT_KEY`); what was done (for generation.json) and that
    no-contact image (None without one)."""
    from .training import CONTACT_KEY

    background, source = dataset_background(DatasetSubset(dataset, train_set.indices), size_hw)
    if background is None:
        if contact:
            raise StageUnavailable(
                f"generator.model.contact_weight needs the no-contact background ({source}); set contact_weight=0"
            )
        warnings.warn(
            f"generator.train.canonical_background: no no-contact background ({source}); training on the raw codes",
            VqtouchWarning,
            stacklevel=2,
        )
        return {"applied": False, "reason": source}, None
    changed = canonicalise_with_background(data, tokenizer, background, contact=contact)
    note = {"applied": True, "cells_changed": round(changed, 4), "background": source}
    if contact:
        note["contact_cells"] = round(float(data.entries[CONTACT_KEY].float().mean()), 4)
    return note, background


def canonicalise_with_background(
    data: CodesDataset, tokenizer: Any, background_3HW: torch.Tensor, *, contact: bool = False
) -> float:
    """``data``'s codes in canonical-background form against ``background_3HW``, in place, with each
    sample's contact cells (:data:`.training.CONTACT_KEY`) when ``contact``; the share of cells changed."""
    from .codes import canonical_background, contact_cells
    from .training import CONTACT_KEY

    data.codes_NHW, changed = canonical_background(data.codes_NHW, tokenizer, background_3HW)
    if contact:
        data.entries[CONTACT_KEY] = contact_cells(data.codes_NHW, tokenizer, background_3HW)
    return changed


def grid_pretraining(
    job: StageJob,
    generator: Any,
    conditioners: Any,
    tokenizer: Any,
    tokenizer_folder: Path,
    data: CodesDataset,
    train_set: Any,
    dataset: Any,
    background_3HW: torch.Tensor | None,
    device: torch.device,
) -> dict[str, Any]:
    """``generator.train.grid_pretrain``: the training split's grid conditions and contact cells, plus
    ``new_scenes`` newly rendered by the dataset (:meth:`new_scenes`), through
    :func:`.grid_pretrain.pretrain_condition_grid`; what was done, for generation.json."""
    from .grid_pretrain import grid_conditioners, pretrain_condition_grid, take
    from .training import CONTACT_KEY

    config, pretrain = job.config, job.section.train.grid_pretrain
    if background_3HW is None or CONTACT_KEY not in data.entries:
        raise StageUnavailable(
            "generator.train.grid_pretrain needs the contact cells (generator.model.contact_weight > 0 and "
            "the dataset's no-contact background); set grid_pretrain.steps=0"
        )
    for module in (generator, *conditioners):
        module.to(device)
    train_index = torch.as_tensor(list(train_set.indices), dtype=torch.long)
    chosen = grid_conditioners(conditioners, take(data.entries, train_index[:1]), pretrain.conditioners)
    keys = list(dict.fromkeys(key for i in chosen for key in conditioners[i].sample_entries()))
    entries = take({key: data.entries[key] for key in keys}, train_index)
    contact_NHW = data.entries[CONTACT_KEY][train_index]
    rendered: dict[str, Any] = {}
    if pretrain.new_scenes:
        entries, contact_NHW, rendered = _with_new_scenes(
            job, tokenizer, tokenizer_folder, dataset, keys, background_3HW, device, entries, contact_NHW
        )
    note = pretrain_condition_grid(
        generator,
        conditioners,
        entries,
        contact_NHW,
        pretrain,
        chosen,
        batch_size=config.data.batch_size,
        seed=config.seed,
        device=device,
    )
    print(
        f"grid pretraining: {note['steps']} steps on {note['scenes']} scenes in {note['seconds']} s, contact "
        f"loss {note['contact_bce_first']} -> {note['contact_bce_last']}"
    )
    return note | rendered


def _with_new_scenes(
    job: StageJob,
    tokenizer: Any,
    tokenizer_folder: Path,
    dataset: Any,
    keys: list[str],
    background_3HW: torch.Tensor,
    device: torch.device,
    entries: dict[str, Any],
    contact_NHW: torch.Tensor,
) -> tuple[dict[str, Any], torch.Tensor, dict[str, Any]]:
    """``entries`` and ``contact_NHW`` followed by those of the dataset's newly rendered scenes; what was rendered."""
    from .codes import dataset_codes
    from .training import CONTACT_KEY

    config, pretrain = job.config, job.section.train.grid_pretrain
    draw = getattr(dataset, "new_scenes", None)
    if draw is None:
        raise StageUnavailable(
            f"generator.train.grid_pretrain.new_scenes={pretrain.new_scenes}, but the dataset "
            f"({type(dataset).__name__}) cannot render new scenes (the procedural one can); set new_scenes=0"
        )
    started = time.perf_counter()
    fresh = draw(pretrain.new_scenes)
    codes_NHW, cache = dataset_codes(
        tokenizer,
        tokenizer_paths(tokenizer_folder),
        fresh,
        {**images_config(config), "new_scenes": pretrain.new_scenes},
        batch_size=config.data.batch_size,
        device=device,
        use_cache=job.section.train.code_cache,
    )
    fresh_data = CodesDataset.collect(codes_NHW, fresh, keys, desc="reading new scenes")
    canonicalise_with_background(fresh_data, tokenizer, background_3HW, contact=True)
    contact_NHW = torch.cat([contact_NHW, fresh_data.entries.pop(CONTACT_KEY)])
    entries = {
        key: torch.cat([entries[key], values]) if isinstance(values, torch.Tensor) else [*entries[key], *values]
        for key, values in fresh_data.entries.items()
    }
    rendered = {
        "new_scenes": pretrain.new_scenes,
        "new_scenes_codes": cache["cache"],
        "new_scenes_seconds": round(time.perf_counter() - started, 1),
    }
    return entries, contact_NHW, rendered


def score_samples(
    job: StageJob, tokenizer: Any, task: GeneratorTask, val_set: Any, train_set: Any, dataset: Any, device: torch.device
) -> dict[str, Any]:
    """The stage's scores: :func:`.scoring.score_generation` of the held-out conditions with the first
    conditioner (``samples.png``) and, for a generator trained with several, with each of them
    (``by_conditioner``); with ``generator.distribution``, the distribution scores too."""
    section, config = job.section, job.config
    metrics = list(
        zip((item.name for item in config.metrics), job.assembly.build_slots(["metrics"]).get("metrics", []))
    )
    # The training split of the dataset itself (the codes dataset's samples hold no images).
    train_images = DatasetSubset(dataset, train_set.indices)
    pool = baseline_pool(train_images)
    background, background_source = dataset_background(train_images, image_hw(config.data.image_size))
    # The held-out samples are read once, and one classifier and one pass over the real images serve
    # every conditioner.
    conditions = held_out_conditions(val_set, dataset, section.num_samples, device)
    scorer = distribution_scorer(conditions, pool, metrics, config.seed) if section.distribution else None
    common = dict(
        generator=task.generator,
        tokenizer=tokenizer,
        sampler=job.assembly.component("generator.sampler"),
        conditions=conditions,
        metrics=metrics,
        background_3HW=background,
        steps=section.steps,
        truncation=section.truncation,
        seed=config.seed,
        device=device,
        precision=sampling_precision(section.sample_precision, device),
        pool=pool,
        distribution=scorer or False,
    )
    names = [item.name for item in config.generator.conditioners]
    first = score_generation(
        conditioner=task.conditioners[0],
        picture=job.run.path / "samples.png",
        guidance=section.guidance_for(names[0]),
        **common,
    )
    scores = {"sampler": section.sampler.name, "conditioner": names[0], "background": background_source, **first}
    if len(names) > 1:
        scores["by_conditioner"] = {f"0:{names[0]}": first} | {
            f"{index}:{name}": score_generation(
                conditioner=conditioner,
                picture=job.run.path / samples_picture(index, name),
                guidance=section.guidance_for(name),
                **common,
            )
            for index, (name, conditioner) in enumerate(zip(names, task.conditioners))
            if index > 0
        }
    return scores


def samples_picture(index: int, name: str) -> str:
    """The file of the sample grid of the generator's conditioner ``index`` (``name``): samples.png for the
    first, whose scores stand in generation.json's top level, samples_<index>_<name>.png for the others."""
    return "samples.png" if index == 0 else f"samples_{index}_{name}.png"


#: The generation scores shown in the run report (generation.json holds them all).
SHOWN_SCORES = (
    "samples",
    "ssim",
    "background_ssim",
    "ceiling_ssim",
    "psnr",
    "background_psnr",
    "ceiling_psnr",
    "contact_psnr",
    "background_contact_psnr",
    "ceiling_contact_psnr",
    "retrieval_contact_psnr",
    "class_mean_contact_psnr",
    "ms_ssim",
    "background_ms_ssim",
    "lpips",
    "background_lpips",
    "clip_score",
    "background_clip_score",
    "real_clip_score",
    "skipped",
    *VERDICT_EVIDENCE,
)
SAMPLES_CAPTION = (
    "One column per held-out sample: its condition when that is an image (top row), the generated "
    "tactile image, then the ground truth (bottom row)."
)


def run_generator_stage(job: StageJob) -> dict[str, Any]:
    """The ``generator`` stage: train, then the sample scores for the report."""
    result = train_generator(job)
    facts = {key: result[key] for key in ("step", "sampler", "steps", "best_step", "split_unit") if key in result}
    metric_names = [metric.name for metric in job.config.metrics]
    if "by_conditioner" in result:  # several conditions: one part each, with its own sample grid
        parts = {}
        for key, scores in result["by_conditioner"].items():
            index, name = key.split(":", 1)
            parts[f"from {name}"] = shown_scores(scores, SHOWN_SCORES, metric_names) | {
                "picture": samples_picture(int(index), name),
                "caption": SAMPLES_CAPTION,
            }
        return {**facts, "parts": parts}
    shown = shown_scores(result, SHOWN_SCORES, metric_names)
    return {**facts, **shown, **({"picture": "samples.png", "caption": SAMPLES_CAPTION} if "samples" in result else {})}

"""The ``generator`` stage: train a generator over a trained tokenizer's codes, then generate and score.

The tokenizer comes from this run (the ``tokenizer`` stage ran before, as in the paper's scenes)
or from another run (``generator.tokenizer_run``, what ``vqtouch train generator --tokenizer RUN``
sets).  Its codes of the whole dataset are computed once and cached (:mod:`.codes`); training
runs through the one trainer (:mod:`.training`), with its checkpoints in
``checkpoints/generator/step-*`` (the tokenizer's stay in ``checkpoints/step-*``).  Afterwards
the held-out conditions are generated with the configured sampler and scored against their
ground-truth tactile images (``generation.json``; ``samples.png``: condition images when there
are, generated, ground truth).
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from vqtouch.core import StageJob, StageUnavailable
from vqtouch.plugins.evaluation.metric_set import MetricSet
from vqtouch.plugins.utils.seeding import resolve_device
from vqtouch.plugins.runtime.run_dir import MissingCheckpointError, RunDir
from vqtouch.plugins.utils.splits import DatasetSubset, experiment_split
from vqtouch.core.errors import VqtouchWarning
from vqtouch.core.image_size import image_hw
from vqtouch.plugins.utils.images import image_grid, save_png
from vqtouch.plugins.training.trainer import Trainer
from vqtouch.plugins.training.checkpoints import apply_ema_weights, step_folders
from vqtouch.plugins.training.precision import autocast, resolve_precision
from vqtouch.plugins.training.batches import collate_samples
from vqtouch.plugins.evaluation.contact import (
    VERDICT_EVIDENCE,
    contact_centroid_errors,
    contact_region_scores,
    dataset_background,
)
from vqtouch.plugins.evaluation.directions import shown_scores

from .best_of import rank_name, sample_best_of
from .stage_plugin import GeneratorSection  # noqa: F401 - re-exported
from .training import CodesDataset, GeneratorTask
from vqtouch.plugins.tokenizer import (
    tokenizer_paths,
    load_tokenizer,
    reconstruct_all,
    tokenizer_digest,
    tokenizer_location,
)

if TYPE_CHECKING:
    from vqtouch.plugins.evaluation.distribution import DistributionScorer


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

    from .codes import dataset_codes

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
    codebook = tokenizer.quantizer.codebook_size
    if getattr(generator, "num_codes", codebook) != codebook:
        raise StageUnavailable(
            f"the generator was built for {generator.num_codes} codes but the tokenizer in "
            f"{tokenizer_folder} has {codebook}; the run's tokenizer section must match that "
            "tokenizer's config"
        )
    dataset = assembly.component("data.dataset")
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
        warnings.warn(
            "a conditioner reads samples' 'tactile' image, which is also the image the generator learns to "
            "produce: it can learn to copy its condition; for touch-to-touch, condition on a second sensor's "
            "image of the same contact (tactile conditioner reads=tactile_source, with paired_sensor set)",
            ConditionIsTargetWarning,
            stacklevel=2,
        )
    data = CodesDataset.collect(codes_NHW, dataset, keys)
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
    trainer = Trainer(
        task,
        train_set,
        section.train,
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
        # The tokenizer is recorded by its step folder, relative to the run when it is the run's own, so
        # that readers use the codes the generator learned even after the tokenizer trains on.
        inside = tokenizer_folder.resolve().is_relative_to(job.run.path.resolve())
        recorded = (
            tokenizer_folder.resolve().relative_to(job.run.path.resolve()) if inside else tokenizer_folder.resolve()
        )
        digest = tokenizer_digest(tokenizer_folder)
        job.publish(
            "generator",
            trainer.last_checkpoint,
            step=state.step,
            tokenizer=recorded.as_posix(),
            tokenizer_sha256=digest,
        )
        if section.num_samples and len(val_set) and section.sampler is not None:
            if trainer.ema and section.sample_weights == "ema":
                # Training is over and its checkpoint written: the stage's samples come from the
                # weights readers will load (load_pipeline prefers the average too).
                for name, module in task.modules.items():
                    apply_ema_weights(module, trainer.ema[name], f"the {name} EMA")
                result["sample_weights"] = "ema"
            result |= score_samples(job, tokenizer, task, val_set, train_set, dataset, device)
        job.run.write_json("generation.json", result)
    return result


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
    from .codes import dataset_codes
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


@torch.no_grad()
def score_generation(
    *,
    generator: Any,
    conditioner: Any,
    tokenizer: Any,
    sampler: Any,
    conditions: HeldOutConditions,
    metrics: list[tuple[str, Any]],
    background_3HW: torch.Tensor | None,
    steps: int,
    guidance: float,
    truncation: float,
    seed: int,
    device: torch.device,
    picture: Path | None = None,
    pool: list[dict[str, Any]] | None = None,
    distribution: bool | DistributionScorer = False,
    best_of: int = 1,
    rank: Any = None,
    precision: str = "fp32",
) -> dict[str, Any]:
    """Generate the held-out ``conditions`` (:func:`held_out_conditions`, read once and shared by every
    conditioner scored) with ``conditioner`` and score them against their ground-truth tactile images.

    Next to each score stand the honest comparisons under the same protocol: the no-contact image
    ``background_3HW`` (``background_*``; none without one: see
    :func:`~vqtouch.plugins.evaluation.contact.dataset_background`), the tokenizer's own reconstruction
    of the ground truth (``ceiling_*``: no generator over these codes can do better) and, given training
    samples (``pool``, see :func:`baseline_pool`), the nearest training image by condition tokens
    (``retrieval_*``) and, for a
    label condition, the mean training image of the label (``class_mean_*``).  Every one is also
    scored on the contact region (``contact_*``).  Sample i is drawn with a generator seeded from
    (seed, its dataset index), so a score does not depend on how many are scored.  ``picture``: where to save
    the sample grid: the conditions (top row, when they are images), generated, ground truth.

    ``distribution``: also score every one of them with :func:`distribution_scorer`'s
    ``fd_effnetlite0`` against the real held-out images and the accuracy of a classifier trained
    on the real training images of ``pool`` (``classifier_accuracy``, beside
    ``real_classifier_accuracy``, the real held-out images' own); a
    :class:`~vqtouch.plugins.evaluation.distribution.DistributionScorer` already fitted on these
    conditions is used as it is.

    A metric that scores images against their conditions rather than their ground truth (one with
    ``condition_scores``, e.g. ``clip_score``) gets the raw conditions instead, for the model's images,
    each comparison and the ground truth itself (``real_*``); conditions it cannot read are listed
    under ``"skipped"`` with the reason.

    ``best_of`` > 1: each sample is the best of that many candidates by ``rank`` (e.g. the code
    judge's, :mod:`.judge`, for a label; :class:`.consensus.ContactConsensus` for any condition), or
    the generator's own posterior of its label when None (:mod:`.best_of`); the scores then say
    ``best_of`` and ``best_of_rank``.  The generator's network samples in ``precision`` (``sampled_in``)."""
    count, indices, truth = len(conditions.indices), conditions.indices, conditions.truth
    batch = conditions.batch(device=device)
    generator.eval()
    conditioner.eval()
    condition = conditioner(conditioner.condition_of(batch))
    images = sample_images(
        generator,
        conditioner,
        tokenizer,
        sampler,
        condition,
        indices,
        steps=steps,
        guidance=guidance,
        truncation=truncation,
        seed=seed,
        device=device,
        best_of=best_of,
        labels_B=conditioner.condition_of(batch) if best_of > 1 else None,
        rank=rank,
        precision=precision,
    )
    scores: dict[str, Any] = {
        "samples": count,
        "steps": steps,
        "guidance": guidance,
        "truncation": truncation,
        "sampled_in": precision,
    }
    if best_of > 1:
        scores["best_of"] = best_of
        scores["best_of_rank"] = rank_name(rank)
    background = None if background_3HW is None else background_3HW.to(truth).expand_as(truth)
    compared = {"": images, "ceiling_": tokenizer.decode_codes(tokenizer.encode_codes(truth))}
    if background is not None:
        compared["background_"] = background
    if pool:
        compared |= training_baselines(conditioner, condition, batch, pool, device)
    scorer = distribution_scorer(conditions, pool, metrics, seed) if distribution is True else distribution or None
    if scorer is not None:
        scores |= scorer.real_scores()
    by_truth = [(name, metric) for name, metric in metrics if not hasattr(metric, "condition_scores")]
    scores |= score_images(compared, truth, by_truth, background, scorer)
    for metric in (metric for _, metric in metrics if hasattr(metric, "condition_scores")):
        found = metric.condition_scores(
            compared | {"real_": truth}, conditioner.condition_of(batch), conditioner.sample_key, conditions.class_names
        )
        if "skipped" in found:
            scores["skipped"] = scores.get("skipped", {}) | found.pop("skipped")
        scores |= found
    if picture is not None:
        columns = min(count, 8)
        shown = condition_images(conditioner, batch)
        rows = ([shown[:columns].float().cpu()] if shown is not None else []) + [
            images[:columns].cpu(),
            truth[:columns].cpu(),
        ]
        save_png(image_grid(torch.cat(rows), columns=columns), picture)
    return scores


def condition_images(conditioner: Any, batch: dict[str, Any]) -> torch.Tensor | None:
    """The conditions of ``batch`` as images (B, 3, H, W) when the conditioner reads an image (a visual
    or a paired sensor's tactile image), for the sample grid; None for labels, texts and others."""
    value = batch.get(conditioner.sample_key)
    if isinstance(value, torch.Tensor) and value.ndim == 4 and value.shape[1] == 3:
        return value
    return None


@dataclass
class HeldOutConditions:
    """The first held-out conditions, read once: their samples as the generator's data gives them
    (condition entries), their dataset indices (each one's sampling seed) and their ground-truth
    tactile images (on the scoring device) with their labels (None without labels) and the dataset's
    class names (what a label means, e.g. for a label's CLIP prompt; empty when unlabelled)."""

    samples: list[dict[str, Any]]
    indices: list[int]
    truth: torch.Tensor
    labels: list[int] | None
    class_names: list[str] = field(default_factory=list)

    def batch(self, start: int = 0, stop: int | None = None, *, device: torch.device) -> dict[str, Any]:
        """Samples ``start:stop`` collated, their tensors on ``device``."""
        batch = collate_samples(self.samples[start:stop])
        return {k: v.to(device) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}


def held_out_conditions(held_out: Any, dataset: Any, count: int, device: torch.device) -> HeldOutConditions:
    """The first ``count`` (at most all) conditions of ``held_out`` (a subset of ``dataset`` with
    ``indices``), with their ground truth and labels read from ``dataset``."""
    from vqtouch.plugins.evaluation.distribution import labels_of

    count = min(count, len(held_out))
    indices = [held_out.indices[i] for i in range(count)]
    real = [dataset[index] for index in indices]
    truth = torch.stack([sample["tactile"] for sample in real]).to(device)
    return HeldOutConditions(
        [held_out[i] for i in range(count)], indices, truth, labels_of(real), list(getattr(dataset, "class_names", []))
    )


@torch.no_grad()
def sample_images(
    generator: Any,
    conditioner: Any,
    tokenizer: Any,
    sampler: Any,
    condition: Any,
    indices: list[int],
    *,
    steps: int,
    guidance: float,
    truncation: float,
    seed: int,
    device: torch.device,
    best_of: int = 1,
    labels_B: torch.Tensor | None = None,
    rank: Any = None,
    precision: str = "fp32",
) -> torch.Tensor:
    """Decoded images (B, 3, H, W) of encoded ``condition`` (one row per entry of ``indices``): row i
    drawn with a generator seeded from (seed, ``indices[i]``), its dataset index.  ``best_of`` > 1
    keeps, per row, the best of that many candidates by ``rank`` (None: the generator's posterior) of
    the row's label ``labels_B`` (:func:`.best_of.sample_best_of`; a label conditioner only).  The
    generator's network runs in ``precision`` (fp32 or bf16, see :func:`sampling_precision`)."""
    null = conditioner.null(len(indices))

    def draw(generators: list[torch.Generator]) -> torch.Tensor:
        with autocast(precision, device):
            return generator.sample(
                condition,
                sampler,
                steps=steps,
                null=null,
                guidance=guidance,
                truncation=truncation,
                generators=generators,
            )

    row_seeds = [seed * 100_003 + index for index in indices]
    return tokenizer.decode_codes(
        sample_best_of(generator, conditioner, labels_B, row_seeds, best_of, draw, device, rank=rank)
    )


#: Sampling precisions: float32, or bfloat16 autocast of the generator's network.
PRECISIONS = ("fp32", "bf16")


def sampling_precision(precision: str, device: torch.device) -> str:
    """The precision (fp32 or bf16) ``generator.sample_precision`` = ``precision`` samples in on ``device``."""
    return resolve_precision(precision, device, "sampling")


@torch.no_grad()
def generate_held_out(
    generator: Any,
    conditioner: Any,
    tokenizer: Any,
    sampler: Any,
    conditions: HeldOutConditions,
    *,
    steps: int,
    guidance: float,
    truncation: float,
    seed: int,
    device: torch.device,
    batch_size: int | None = None,
    precision: str = "fp32",
    best_of: int = 1,
    rank: Any = None,
) -> torch.Tensor:
    """Float32 images (N, 3, H, W) of ``conditions``, encoded and sampled ``batch_size`` at a time
    (None: all at once, as :func:`score_generation` does), the network in ``precision`` (``fp32``, or
    ``bf16`` autocast), each the best of ``best_of`` candidates by ``rank`` (label conditions; :mod:`.best_of`); the
    seeds of :func:`sample_images`, so image i does not depend on the batching beyond float
    rounding.  What ``vqtouch tradeoff generator`` times."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision {precision!r}: expected one of {', '.join(PRECISIONS)}")
    generator.eval()
    conditioner.eval()
    count = len(conditions.indices)
    size = batch_size or count
    images = []
    for start in range(0, count, size):
        batch = conditions.batch(start, start + size, device=device)
        condition = conditioner(conditioner.condition_of(batch))
        images.append(
            sample_images(
                generator,
                conditioner,
                tokenizer,
                sampler,
                condition,
                conditions.indices[start : start + size],
                steps=steps,
                guidance=guidance,
                truncation=truncation,
                seed=seed,
                device=device,
                best_of=best_of,
                labels_B=conditioner.condition_of(batch) if best_of > 1 else None,
                rank=rank,
                precision=precision,
            ).float()
        )
    return torch.cat(images)


def distribution_scorer(
    conditions: HeldOutConditions,
    pool: list[dict[str, Any]] | None,
    metrics: list[tuple[str, Any]],
    seed: int,
    tokenizer: Any = None,
) -> DistributionScorer:
    """The distribution scores of ``conditions``: ``fd_effnetlite0`` against their ground truth and
    a classifier trained on the real training images of ``pool`` (their dataset labels).  The
    features are those of the ``fd_effnetlite0`` metric among ``metrics`` (its options), else of
    one with its defaults (224 px).

    Given a ``tokenizer``, the classifier trains on its reconstructions of those training images
    instead: a classifier fitted on sharp real images can fail on every decoded image (the
    tokenizer's own reconstructions included, the ceiling), which says more about the decoder's
    blur than about whether a sample shows its class."""
    from vqtouch.plugins.evaluation.distribution import DistributionScorer, labels_of

    metric = next((metric for name, metric in metrics if name == "fd_effnetlite0"), None)
    pool = pool or []
    images = [sample["tactile"] for sample in pool]
    if tokenizer is not None and images:
        images = list(reconstruct_all(tokenizer, torch.stack(images).to(tokenizer.device), 64).float().cpu())
    return DistributionScorer(
        conditions.truth, conditions.labels, images, labels_of(pool) if pool else None, metric=metric, seed=seed
    )


def score_images(
    candidates: dict[str, torch.Tensor],
    truth_B3HW: torch.Tensor,
    metrics: list[tuple[str, Any]],
    background_B3HW: torch.Tensor | None = None,
    distribution: DistributionScorer | None = None,
) -> dict[str, Any]:
    """Scores of each candidate image set (``{prefix: images}``, image i for held-out condition i)
    against the ground truth: ``{prefix}{metric}`` for each metric, the contact-region scores (given
    the no-contact image) and, given a scorer, ``{prefix}fd_effnetlite0`` and
    ``{prefix}classifier_accuracy`` (the scorer's ``fd_effnetlite0`` stands for the metric of that
    name: the same quantity, its real features computed once).  A metric that cannot run here is
    listed under ``"skipped"`` with its reason."""
    scores: dict[str, Any] = {}
    metric_set = MetricSet(
        (name, metric) for name, metric in metrics if distribution is None or name != "fd_effnetlite0"
    )
    for prefix, predicted in candidates.items():
        scores |= metric_set.score(predicted.cpu(), truth_B3HW.cpu(), prefix)
    if background_B3HW is not None:
        scores |= contact_region_scores(candidates, truth_B3HW, background_B3HW)
        scores |= contact_centroid_errors(candidates, truth_B3HW, background_B3HW)
    if distribution is not None:
        for prefix, predicted in candidates.items():
            scores |= distribution.score(predicted, prefix)
    return scores


#: The most training samples the retrieval and class-mean baselines look at (the first ones of
#: the split): their tactile images are held in memory.
BASELINE_POOL = 2000


def baseline_pool(train: Any) -> list[dict[str, Any]]:
    """The training samples the baselines compare with: the first ``BASELINE_POOL`` of ``train``,
    read once per scoring (a mixed generator's conditioners share them)."""
    return [train[i] for i in range(min(len(train), BASELINE_POOL))]


@torch.no_grad()
def training_baselines(
    conditioner: Any, condition: Any, batch: dict[str, Any], pool: list[dict[str, Any]], device: torch.device
) -> dict[str, torch.Tensor]:
    """Baselines from training samples (``pool``): for each held-out condition, the training tactile
    image whose condition tokens are nearest (cosine similarity of the mean token; ties go to the
    earlier sample), and for labels the mean training image of the label (the mean of all pool
    images for a label the pool lacks)."""
    images_N3HW = torch.stack([sample["tactile"] for sample in pool]).to(device)
    entries = conditioner.sample_entries()
    keys_ND = []
    for start in range(0, len(pool), 64):
        chunk = collate_samples([{key: sample[key] for key in entries} for sample in pool[start : start + 64]])
        chunk = {k: v.to(device) if isinstance(v, torch.Tensor) else v for k, v in chunk.items()}
        keys_ND.append(conditioner(conditioner.condition_of(chunk)).tokens_BND.float().mean(dim=1))
    similarity_BN = (
        torch.nn.functional.normalize(condition.tokens_BND.float().mean(dim=1), dim=-1)
        @ torch.nn.functional.normalize(torch.cat(keys_ND), dim=-1).T
    )
    # argmax returns the first of equal maxima: a label's nearest is its first training image.
    baselines = {"retrieval_": images_N3HW[similarity_BN.argmax(dim=1)]}
    if conditioner.sample_key == "label":
        labels_N = torch.as_tensor([int(sample["label"]) for sample in pool], device=device)
        overall = images_N3HW.mean(dim=0)
        means = [
            images_N3HW[labels_N == int(label)].mean(dim=0) if bool((labels_N == int(label)).any()) else overall
            for label in batch["label"]
        ]
        baselines["class_mean_"] = torch.stack(means)
    return baselines


def score_samples(
    job: StageJob, tokenizer: Any, task: GeneratorTask, val_set: Any, train_set: Any, dataset: Any, device: torch.device
) -> dict[str, Any]:
    """The stage's scores: :func:`score_generation` of the held-out conditions with the first
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

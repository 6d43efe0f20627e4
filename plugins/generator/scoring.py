"""Generating held-out conditions and scoring them against their ground truth.

The generator stage, ``vqtouch evaluate generation``, the pretrained stage and the sampling sweep
(:mod:`.tradeoff`) all generate and score through these functions, with the same per-sample seeds.

Next to each score of the generated images (:func:`score_generation`) stand the honest comparisons
under the same protocol: the no-contact image (``background_*``; none without one: see
:func:`~vqtouch.plugins.evaluation.contact.dataset_background`), the tokenizer's own reconstruction
of the ground truth (``ceiling_*``: no generator over these codes can do better) and, given training
samples (see :func:`baseline_pool`), the nearest training image by condition tokens
(``retrieval_*``) and, for a label condition, the mean training image of the label
(``class_mean_*``).  Every one is also scored on the contact region (``contact_*``).

The distribution scores (:func:`distribution_scorer`) are ``fd_effnetlite0`` against the real
held-out images and the accuracy of a classifier trained on the real training images
(``classifier_accuracy``, beside ``real_classifier_accuracy``, the real held-out images' own).

A metric that scores images against their conditions rather than their ground truth (one with
``condition_scores``, e.g. ``clip_score``) gets the raw conditions instead, for the model's images,
each comparison and the ground truth itself (``real_*``); conditions it cannot read are listed
under ``"skipped"`` with the reason.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from vqtouch.plugins.evaluation.contact import contact_centroid_errors, contact_region_scores
from vqtouch.plugins.evaluation.metric_set import MetricSet
from vqtouch.plugins.tokenizer import reconstruct_all
from vqtouch.plugins.training.batches import collate_samples
from vqtouch.plugins.training.precision import autocast, resolve_precision
from vqtouch.plugins.utils.images import image_grid, save_png

from .best_of import rank_name, sample_best_of

if TYPE_CHECKING:
    from vqtouch.plugins.evaluation.distribution import DistributionScorer


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
    conditioner scored) with ``conditioner`` and score them against their ground-truth tactile images,
    beside the comparisons of the module docstring: ``background_*`` from ``background_3HW``,
    ``ceiling_*`` and, given training samples ``pool`` (see :func:`baseline_pool`), ``retrieval_*``
    and ``class_mean_*``.  Sample i is drawn with a generator seeded from (seed, its dataset index),
    so a score does not depend on how many are scored.  ``picture``: where to save the sample grid:
    the conditions (top row, when they are images), generated, ground truth.

    ``distribution``: True to also score every one of them with :func:`distribution_scorer` (its
    classifier trained on the real training images of ``pool``), or a
    :class:`~vqtouch.plugins.evaluation.distribution.DistributionScorer` already fitted on these
    conditions, used as it is.

    ``best_of`` > 1: each sample is the best of that many candidates by ``rank`` (e.g. the code
    judge's, :mod:`.judge`, for a label; :class:`.consensus.ContactConsensus` for any condition), or
    the generator's own posterior of its label when None (:mod:`.best_of`); the scores then say
    ``best_of`` and ``best_of_rank``.  The generator's network samples in ``precision`` (``sampled_in``)."""
    count, truth = len(conditions.indices), conditions.truth
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
        conditions.indices,
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
    scores = _sampling_facts(count, steps, guidance, truncation, precision, best_of, rank)
    background = None if background_3HW is None else background_3HW.to(truth).expand_as(truth)
    compared = _comparisons(images, truth, tokenizer, background, conditioner, condition, batch, pool, device)
    scorer = distribution_scorer(conditions, pool, metrics, seed) if distribution is True else distribution or None
    scores |= _quality_scores(compared, conditions, conditioner, batch, metrics, background, scorer)
    if picture is not None:
        _save_sample_grid(picture, conditioner, batch, images, truth, count)
    return scores


def _sampling_facts(
    count: int, steps: int, guidance: float, truncation: float, precision: str, best_of: int, rank: Any
) -> dict[str, Any]:
    """How the scored samples were drawn, the first entries of their scores."""
    facts: dict[str, Any] = {
        "samples": count,
        "steps": steps,
        "guidance": guidance,
        "truncation": truncation,
        "sampled_in": precision,
    }
    if best_of > 1:
        facts["best_of"] = best_of
        facts["best_of_rank"] = rank_name(rank)
    return facts


def _comparisons(
    images: torch.Tensor,
    truth: torch.Tensor,
    tokenizer: Any,
    background: torch.Tensor | None,
    conditioner: Any,
    condition: Any,
    batch: dict[str, Any],
    pool: list[dict[str, Any]] | None,
    device: torch.device,
) -> dict[str, torch.Tensor]:
    """The generated images by key prefix, beside the ceiling, the no-contact image and the training baselines."""
    compared = {"": images, "ceiling_": tokenizer.decode_codes(tokenizer.encode_codes(truth))}
    if background is not None:
        compared["background_"] = background
    if pool:
        compared |= training_baselines(conditioner, condition, batch, pool, device)
    return compared


def _quality_scores(
    compared: dict[str, torch.Tensor],
    conditions: HeldOutConditions,
    conditioner: Any,
    batch: dict[str, Any],
    metrics: list[tuple[str, Any]],
    background: torch.Tensor | None,
    scorer: DistributionScorer | None,
) -> dict[str, Any]:
    """The scores of every compared image set: against the ground truth, the real distribution and the conditions."""
    scores: dict[str, Any] = {}
    if scorer is not None:
        scores |= scorer.real_scores()
    by_truth = [(name, metric) for name, metric in metrics if not hasattr(metric, "condition_scores")]
    scores |= score_images(compared, conditions.truth, by_truth, background, scorer)
    for metric in (metric for _, metric in metrics if hasattr(metric, "condition_scores")):
        found = metric.condition_scores(
            compared | {"real_": conditions.truth},
            conditioner.condition_of(batch),
            conditioner.sample_key,
            conditions.class_names,
        )
        if "skipped" in found:
            scores["skipped"] = scores.get("skipped", {}) | found.pop("skipped")
        scores |= found
    return scores


def _save_sample_grid(
    picture: Path, conditioner: Any, batch: dict[str, Any], images: torch.Tensor, truth: torch.Tensor, count: int
) -> None:
    """Save up to 8 columns: the conditions when they are images (top row), generated, ground truth."""
    columns = min(count, 8)
    shown = condition_images(conditioner, batch)
    rows = ([shown[:columns].float().cpu()] if shown is not None else []) + [
        images[:columns].cpu(),
        truth[:columns].cpu(),
    ]
    save_png(image_grid(torch.cat(rows), columns=columns), picture)


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

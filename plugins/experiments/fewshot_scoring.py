"""Steps 3 and 4 of ``vqtouch fewshot`` (:mod:`vqtouch.plugins.experiments.fewshot_generation`): every
condition sampled by the fine-tuned and the zero-shot family generator, and the samples scored against
the new sensor's held-out images, its paired images of the same contacts and a classifier of them."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Sequence

import torch

from vqtouch.core import Assembly, ConfigError, PluginHost
from vqtouch.plugins.data.sensor_folders import folder_of
from vqtouch.plugins.utils.images import image_grid, save_png
from vqtouch.plugins.utils.splits import experiment_split

#: The scores of a row, and their headers.
SCORE_KEYS = ("fd_effnetlite0", "contact_psnr", "classifier_accuracy")
SCORE_HEADERS = {
    "fd_effnetlite0": "fd_effnetlite0 ↓",
    "contact_psnr": "contact PSNR ↑ (paired)",
    "classifier_accuracy": "classifier acc. ↑ (paired)",
}
#: The new sensor's images of the family's training scenes the classifier learns (at most).
CLASSIFIER_IMAGES = 512
#: What the classifier accuracy is, for the tables.
CLASSIFIER_TEXT = (
    "classifier accuracy: how often a classifier trained on the adapted tokenizer's reconstructions of the new "
    "sensor's images of the family's training scenes names each sample's condition class (its ceiling: the same "
    "on the reconstructions of the sensor's images of the held-out conditions; chance: one over the classes):"
)
#: The row of the classifier's ceiling: the adapted tokenizer's reconstructions of the paired truth.
RECONSTRUCTED = "new sensor, reconstructed (ceiling)"
#: The arms every conditioner's samples are scored beside.
ARMS = ("few-shot", "zero-shot", "shots (copied)", "no-contact background")


def _cycled(images_N3HW: torch.Tensor, count: int) -> torch.Tensor:
    """``count`` images: ``images_N3HW`` repeated as often as it takes."""
    return images_N3HW.repeat(-(-count // len(images_N3HW)), 1, 1, 1)[:count]


def _samples(pipe: Any, index: int, conditions: Any, seed: int, device: torch.device, batch_size: int) -> torch.Tensor:
    """Pipeline ``pipe``'s images of ``conditions`` from conditioner ``index`` at its default settings."""
    from vqtouch.plugins.generator import sample_images

    conditioner = pipe.conditioners[index]
    images = []
    for start in range(0, len(conditions.indices), batch_size):
        batch = conditions.batch(start, start + batch_size, device=device)
        with torch.no_grad():
            tokens = conditioner(conditioner.condition_of(batch))
            images.append(
                sample_images(
                    pipe.generator,
                    conditioner,
                    pipe.tokenizer,
                    pipe.sampler,
                    tokens,
                    conditions.indices[start : start + batch_size],
                    steps=pipe.settings["steps"],
                    guidance=pipe.guidance_for(index),
                    truncation=pipe.settings["truncation"],
                    seed=seed,
                    device=device,
                    precision=pipe.sample_precision,
                )
                .float()
                .clamp(0, 1)
                .cpu()
            )
    return torch.cat(images)


def paired_truth(config: Any, images: str, indices: Sequence[int], host: PluginHost) -> torch.Tensor | None:
    """The new sensor's images of the held-out conditions' own contacts, when they exist: the family's
    data rendered by that sensor (``images`` a registered sensor or variant whose family renders; None
    for a folder of captured images, which pairs with nothing)."""
    from vqtouch.core import VqtouchError, validate_experiment

    if folder_of(images) is not None:
        return None
    spec = json.loads(images) if images.strip().startswith("{") else {"name": images}
    data = config.to_dict() | {"sensor": spec}
    try:
        rendered = Assembly(validate_experiment(data, host), host).component("data.dataset")
    except VqtouchError:
        return None
    if rendered.rendering_sensor() is None:
        return None
    return torch.stack([rendered[index]["tactile"] for index in indices]).float()


def sample_and_score(
    pipe: Any,
    family_pipe: Any,
    images: str,
    name: str,
    out: Path,
    host: PluginHost,
    *,
    held_out_M3HW: torch.Tensor,
    shots_N3HW: torch.Tensor,
    background_3HW: torch.Tensor,
    samples: int,
    seed: int,
    feature_size: int,
    score: bool = True,
    report: Any = print,
) -> dict[str, Any]:
    """Steps 3 and 4: sample every condition with the fine-tuned ``pipe`` and the zero-shot ``family_pipe``
    (pictures into ``out``) and score them; the ``conditioners``, ``samples`` and ``scores`` entries of
    ``fewshot.json``.  Draws depend on ``seed`` and each condition's index only, so scoring a finished
    run again draws the same images."""
    config = family_pipe.config
    train, conditions = _family_conditions(family_pipe, host, min(samples, len(held_out_M3HW)))
    count = len(conditions.indices)
    real_M3HW = held_out_M3HW[:count]
    names = pipe.conditioner_names()
    report(f"3/5 sample {count} images of the new sensor from each condition ({', '.join(names)})")
    generated = _sample_conditions(pipe, family_pipe, names, conditions, real_M3HW, seed, out)
    result: dict[str, Any] = {"conditioners": names, "samples": _samples_entry(names, count)}
    if not score:
        report("4/5 scoring skipped (--no-score)")
        return result | {"scores": []}
    paired = paired_truth(config, images, conditions.indices, host)
    classifier = None
    if paired is not None and conditions.labels is not None:
        classifier = classifier_images(config, images, train, pipe.tokenizer, host)
    report(_scoring_line(count, name, feature_size, paired is not None, classifier))
    result["paired_truth"] = paired is not None
    result["classifier"] = (
        {"train_images": len(classifier[1]), "trained_on": "the adapted tokenizer's reconstructions"}
        if classifier is not None
        else {"skipped": "no paired truth with labels (a folder of captured images, or a dataset without labels)"}
    )
    # One feature network (its weights loaded once) for the fd and the classifier.
    metric = host.build("metric", {"name": "fd_effnetlite0", "image_size": feature_size})
    scores = _scores(generated, real_M3HW, shots_N3HW, background_3HW, metric, paired)
    if classifier is not None:
        accuracy = _classifier_scores(generated, paired, conditions.labels, classifier, pipe.tokenizer, metric, seed)
        _add_accuracy(scores, accuracy)
    return result | {"scores": scores}


def _family_conditions(family_pipe: Any, host: PluginHost, count: int) -> tuple[Any, Any]:
    """The family data's training split and up to ``count`` of its held-out conditions; a one-line
    ConfigError when it holds none."""
    from vqtouch.plugins.generator import held_out_conditions

    config = family_pipe.config
    dataset = Assembly(config, host).component("data.dataset")
    train, held_out = experiment_split(dataset, config.data, config.seed)
    conditions = held_out_conditions(held_out, dataset, count, family_pipe.device)
    if len(conditions.indices) == 0:
        raise ConfigError("the family's data hold no held-out conditions to generate from")
    return train, conditions


def _sample_conditions(
    pipe: Any, family_pipe: Any, names: Sequence[str], conditions: Any, real_M3HW: torch.Tensor, seed: int, out: Path
) -> dict[str, dict[str, torch.Tensor]]:
    """Conditioner (of ``names``) -> arm -> the few-shot and zero-shot images of every condition; writes each
    conditioner's ``samples_<i>_<name>.png`` and the overview ``samples.png`` into ``out``."""
    device = family_pipe.device
    generated: dict[str, dict[str, torch.Tensor]] = {}
    shown = min(len(conditions.indices), 8)
    overview: list[torch.Tensor] = []  # samples.png: each condition's row(s), then the real images
    for index, label in enumerate(names):
        fewshot_images = _samples(pipe, index, conditions, seed, device, 16)
        zero_shot_images = _samples(family_pipe, index, conditions, seed, device, 16)
        generated[label] = {"few-shot": fewshot_images, "zero-shot": zero_shot_images}
        rows = []
        batch = conditions.batch(0, shown, device=torch.device("cpu"))
        condition = batch.get(pipe.conditioners[index].sample_key)
        if isinstance(condition, torch.Tensor) and condition.ndim == 4 and condition.shape[1] == 3:
            rows.append(condition.float())
        overview += [*rows, fewshot_images[:shown]]
        rows += [fewshot_images[:shown], zero_shot_images[:shown], real_M3HW[:shown].float()]
        save_png(image_grid(torch.cat(rows), columns=shown), out / f"samples_{label.replace(':', '_')}.png")
    save_png(image_grid(torch.cat([*overview, real_M3HW[:shown].float()]), columns=shown), out / "samples.png")
    return generated


def _samples_entry(names: Sequence[str], count: int) -> dict[str, Any]:
    """``fewshot.json``'s ``samples``: how many per arm, the pictures and what their rows are."""
    return {
        "count": count,
        "pictures": [f"samples_{label.replace(':', '_')}.png" for label in names],
        "overview": "samples.png",
        "rows": "condition (image conditions only) | few-shot | zero-shot | real new-sensor image",
    }


def _scoring_line(
    count: int, name: str, feature_size: int, paired: bool, classifier: tuple[torch.Tensor, list[int]] | None
) -> str:
    """Step 4's line: what the samples are scored against."""
    return (
        f"4/5 score against {count} held-out images of {name} (fd_effnetlite0 at {feature_size} px"
        + ("; contact PSNR against its rendering of each condition's own contact" if paired else "")
        + (
            f"; a classifier trained on the adapted tokenizer's reconstructions of {len(classifier[1])} of its "
            "images of the family's training scenes)"
            if classifier is not None
            else ")"
        )
    )


def _add_accuracy(scores: list[dict[str, Any]], accuracy: dict[tuple[str, str], float]) -> None:
    """Each (conditioner, arm)'s classifier accuracy into its row of ``scores``, a new row for those
    without one (the ceiling)."""
    for row in scores:
        if (row["conditioner"], row["arm"]) in accuracy:
            row["classifier_accuracy"] = accuracy.pop((row["conditioner"], row["arm"]))
    scores += [
        {"conditioner": label, "arm": arm, "classifier_accuracy": value} for (label, arm), value in accuracy.items()
    ]


@torch.no_grad()
def classifier_images(
    config: Any, images: str, train: Any, tokenizer: Any, host: PluginHost
) -> tuple[torch.Tensor, list[int]] | None:
    """What the samples' classifier learns: the new sensor's images of the family's first
    :data:`CLASSIFIER_IMAGES` training scenes (``images`` a registered sensor that renders them),
    decoded through the adapted ``tokenizer`` (a classifier fitted on sharp images fails on every
    decoded one, the tokenizer's own reconstructions included), with the scenes' labels; None when
    the sensor renders nothing or the scenes carry no labels."""
    from vqtouch.plugins.evaluation.distribution import labels_of
    from vqtouch.plugins.tokenizer import reconstruct_all

    indices = list(train.indices[:CLASSIFIER_IMAGES])
    labels = labels_of([train.dataset[index] for index in indices])
    rendered = paired_truth(config, images, indices, host) if labels is not None else None
    if rendered is None or len(set(labels)) < 2:
        return None
    return reconstruct_all(tokenizer, rendered.to(tokenizer.device)).float().cpu(), labels


@torch.no_grad()
def _classifier_scores(
    generated: dict[str, dict[str, torch.Tensor]],
    paired_M3HW: torch.Tensor,
    labels: Sequence[int],
    classifier: tuple[torch.Tensor, list[int]],
    tokenizer: Any,
    metric: Any,
    seed: int,
) -> dict[tuple[str, str], float]:
    """``classifier_accuracy`` per (conditioner, arm): how often the classifier of
    :func:`classifier_images` names the class of the arm's samples (sample i's class is held-out
    condition i's), and per conditioner under :data:`RECONSTRUCTED` its ceiling, the same on the
    adapted tokenizer's reconstructions of the new sensor's images of those very conditions."""
    from vqtouch.plugins.evaluation.distribution import DistributionScorer
    from vqtouch.plugins.tokenizer import reconstruct_all

    scorer = DistributionScorer(paired_M3HW, list(labels), classifier[0], classifier[1], metric=metric, seed=seed)
    ceiling = scorer.score(reconstruct_all(tokenizer, paired_M3HW.to(tokenizer.device)).float().cpu())
    accuracy = {}
    for label, arms in generated.items():
        for arm, images in arms.items():
            accuracy[(label, arm)] = scorer.score(images)["classifier_accuracy"]
        accuracy[(label, RECONSTRUCTED)] = ceiling["classifier_accuracy"]
    return accuracy


def _scores(
    generated: dict[str, dict[str, torch.Tensor]],
    real_M3HW: torch.Tensor,
    shots_N3HW: torch.Tensor,
    background_3HW: torch.Tensor,
    metric: Any,
    paired_M3HW: torch.Tensor | None = None,
) -> list[dict[str, Any]]:
    """One row per conditioner and arm: ``fd_effnetlite0`` against the held-out real images and, given
    the new sensor's images of the same contacts (``paired_M3HW``), the contact-region PSNR against them
    (the background's beside it; copied shots have no pairing)."""
    from vqtouch.plugins.evaluation.contact import contact_region_scores
    from vqtouch.plugins.evaluation.distribution import DistributionScorer

    count = len(real_M3HW)
    scorer = DistributionScorer(real_M3HW.float(), metric=metric)
    common = {
        "shots (copied)": scorer.score(_cycled(shots_N3HW.float(), count))["fd_effnetlite0"],
        "no-contact background": scorer.score(background_3HW.float().expand(count, -1, -1, -1))["fd_effnetlite0"],
    }
    rows = []
    for label, arms in generated.items():
        contact: dict[str, float] = {}
        if paired_M3HW is not None:
            background = background_3HW.float().expand(count, -1, -1, -1)
            found = contact_region_scores({**arms, "no-contact background": background}, paired_M3HW, background)
            contact = {arm: round(found[f"{arm}contact_psnr"], 4) for arm in (*arms, "no-contact background")}
        for arm, images in arms.items():
            row = {"conditioner": label, "arm": arm, "fd_effnetlite0": scorer.score(images)["fd_effnetlite0"]}
            rows.append(row | ({"contact_psnr": contact[arm]} if contact else {}))
        for arm, value in common.items():
            row = {"conditioner": label, "arm": arm, "fd_effnetlite0": value}
            rows.append(row | ({"contact_psnr": contact[arm]} if arm in contact else {}))
    return rows

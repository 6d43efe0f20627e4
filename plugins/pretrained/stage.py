"""The ``pretrained`` stage: the bundled checkpoints on this run's held-out data.

It loads a bundle (:mod:`.bundle`), reconstructs the run's held-out images with its tokenizer
and generates the held-out conditions from each of its conditioners, scoring both exactly like
the ``tokenizer`` and ``generator`` stages do (with the no-contact background and contact-region
scores beside every score).  Nothing is trained; the report says the weights are bundled, which
command trained them and at which step.

It refuses (as "cannot run", with the reason) a scene whose data the bundle cannot speak for: another
image size, sensor or paired sensor, other class names, or a conditioner kind the scene's data
does not provide, and a scene whose dataset is the one the bundle was trained on (its "held-out"
images could be the bundle's training images).
"""

from __future__ import annotations

from typing import Any

from vqtouch.core import ConfigError, StageJob, StageUnavailable, validate_experiment
from vqtouch.plugins.evaluation.metric_set import MetricSet
from vqtouch.plugins.utils.seeding import resolve_device
from vqtouch.plugins.utils.splits import DatasetSubset, experiment_split
from vqtouch.core.image_size import image_hw
from vqtouch.plugins.evaluation.contact import dataset_background
from vqtouch.plugins.evaluation.directions import shown_scores

from .bundle import Bundle, bundle_folder, load_bundle
from .stage_plugin import PretrainedSection  # noqa: F401 - re-exported
from vqtouch.plugins.generator import (
    GENERATION_SHOWN_SCORES,
    SAMPLES_CAPTION,
    baseline_pool,
    held_out_conditions,
    sampling_precision,
    score_generation,
)
from vqtouch.plugins.tokenizer import TOKENIZER_SHOWN_SCORES, evaluate_reconstruction, printable, save_pairs

#: The folder of the stage's pictures inside the run.
PICTURES = "pretrained"


def _compared(config: dict[str, Any]) -> dict[str, Any]:
    data = config.get("data", {})
    dataset = data.get("dataset") or {}
    return {
        "data.image_size": data.get("image_size"),
        "sensor": config.get("sensor"),
        "paired_sensor": config.get("paired_sensor"),
        "data.dataset.name": dataset.get("name"),
        "data.dataset.classes": dataset.get("classes"),
    }


def check_compatible(bundle: Bundle, config: Any) -> None:
    """Refuse (StageUnavailable) a scene whose data the bundle was not trained for, or was trained on."""
    trained, scene = bundle.run_config, config.to_dict()
    wanted, given = _compared(trained), _compared(scene)
    differences = [
        f"{key}: bundle {value!r}, scene {given[key]!r}" for key, value in wanted.items() if given[key] != value
    ]
    if differences:
        raise StageUnavailable(
            f"bundle {bundle.name!r} was trained for other data ({'; '.join(differences)}); "
            "retrain one for this scene with `vqtouch pretrained export`"
        )
    trained_data, scene_data = dict(trained["data"]["dataset"]), dict(scene["data"]["dataset"])
    trained_data.pop("num_samples", None), scene_data.pop("num_samples", None)
    if trained_data == scene_data:
        raise StageUnavailable(
            f"bundle {bundle.name!r} was trained on this scene's very dataset, so its held-out "
            "split may hold the bundle's training images; set another data.dataset.seed"
        )


def _open_bundle(job: StageJob) -> tuple[Bundle, Any]:
    """The section's bundle, checked against the scene (StageUnavailable when it cannot speak for it),
    and the device it was loaded on."""
    section = job.section
    try:
        folder = bundle_folder(section.bundle)
    except ConfigError as exc:
        raise StageUnavailable(str(exc)) from None
    device = resolve_device(job.config.device)
    bundle = load_bundle(section.bundle, job.host, device=device, root=folder.parent)
    check_compatible(bundle, job.config)
    return bundle, device


def _score_tokenizer(
    job: StageJob, bundle: Bundle, held_out: Any, metrics: list[tuple[str, Any]], device: Any, background: Any
) -> dict[str, Any]:
    """The bundled tokenizer's scores on ``held_out``, with its reconstructions picture."""
    config = job.config
    scores = evaluate_reconstruction(
        bundle.tokenizer,
        held_out,
        MetricSet(metrics),
        device=device,
        batch_size=config.data.batch_size,
        background_3HW=background,
    )
    save_pairs(*scores.pop("examples"), job.run.path / PICTURES / "reconstructions.png")
    return {
        **shown_scores(printable(scores), TOKENIZER_SHOWN_SCORES, [name for name, _ in metrics]),
        "picture": f"{PICTURES}/reconstructions.png",
        "caption": "Held-out images of this run (top row) above the bundled tokenizer's reconstructions (bottom row).",
    }


def _score_generators(
    job: StageJob,
    bundle: Bundle,
    dataset: Any,
    train_set: Any,
    val_set: Any,
    metrics: list[tuple[str, Any]],
    device: Any,
    background: Any,
) -> dict[str, Any]:
    """The bundled generator's scores from each bundled conditioner, keyed by the report's part name."""
    config, section = job.config, job.section
    conditions = held_out_conditions(val_set, dataset, section.num_samples, device)
    missing = [
        name
        for name, conditioner in zip(bundle.conditioner_names, bundle.conditioners)
        if not all(key in conditions.samples[0] for key in conditioner.sample_entries())
    ]
    if missing:
        raise StageUnavailable(
            f"this scene's samples lack what bundled conditioner(s) {', '.join(missing)} read; "
            "use a scene with a paired sensor and visual images (e.g. tour)"
        )
    pool = baseline_pool(DatasetSubset(dataset, train_set.indices))
    sampler = job.host.build("sampler", section.sampler)
    # Each conditioner at the bundle's own default guidance (its recorded run config, validated).
    sampling = validate_experiment(bundle.run_config, job.host).generator
    parts: dict[str, Any] = {}
    for index, (name, conditioner) in enumerate(zip(bundle.conditioner_names, bundle.conditioners)):
        picture = f"{PICTURES}/samples_{index}_{name}.png"
        generated = score_generation(
            generator=bundle.generator,
            conditioner=conditioner,
            tokenizer=bundle.tokenizer,
            sampler=sampler,
            conditions=conditions,
            metrics=metrics,
            background_3HW=background,
            steps=section.steps,
            guidance=sampling.guidance_for(name),
            truncation=1.0,
            seed=config.seed,
            device=device,
            picture=job.run.path / picture,
            pool=pool,
            precision=sampling_precision(sampling.sample_precision, device),
        )
        parts[f"bundled generator from {name}"] = shown_scores(
            generated, GENERATION_SHOWN_SCORES, [name for name, _ in metrics]
        ) | {"picture": picture, "caption": SAMPLES_CAPTION}
    return parts


def run_pretrained_stage(job: StageJob) -> dict[str, Any]:
    """Load the bundle, check it fits the scene, score its tokenizer and each of its conditioners."""

    config, section = job.config, job.section
    bundle, device = _open_bundle(job)
    dataset = job.assembly.component("data.dataset")
    train_set, val_set = experiment_split(dataset, config.data, config.seed)
    if len(val_set) == 0:
        raise StageUnavailable(f"no held-out samples to score (data.val_fraction={config.data.val_fraction:g})")
    metrics = list(
        zip((item.name for item in config.metrics), job.assembly.build_slots(["metrics"]).get("metrics", []))
    )
    held_out = DatasetSubset(dataset, val_set.indices[: section.num_samples])
    (job.run.path / PICTURES).mkdir(exist_ok=True)

    background, background_source = dataset_background(train_set, image_hw(config.data.image_size))
    parts: dict[str, Any] = {
        "bundled tokenizer": _score_tokenizer(job, bundle, held_out, metrics, device, background),
        **_score_generators(job, bundle, dataset, train_set, val_set, metrics, device, background),
    }
    return {
        "bundle": bundle.name,
        "bundled": True,
        "megabytes": round(bundle.size_bytes / 1e6, 2),
        "tokenizer_step": bundle.tokenizer_step,
        "generator_step": bundle.generator_step,
        "tokenizer_trained_by": bundle.tokenizer_command,
        "generator_trained_by": bundle.generator_command,
        "sampler": section.sampler,
        "steps": section.steps,
        "background": background_source,
        "parts": parts,
    }

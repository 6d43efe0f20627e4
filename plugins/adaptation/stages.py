"""The ``cluster`` and ``adapt`` stages.

- ``cluster`` groups sensors into families from the run's tokenizer features (its
  ``cluster.clusterer`` slot): by default every registered sensor family and a few random
  environmental variants of each.  With a ``target_sensor`` it also assigns that unseen sensor to
  a family (or refuses it) and scores the family tokenizer on its images zero-shot.  Writes
  ``<run>/cluster/`` (cluster.json, clusterer.safetensors, families.png).
- ``adapt`` fine-tunes the run's tokenizer (the family tokenizer) with a few images of the
  ``target_sensor`` mixed 1:ratio with family data (:mod:`.adapt`) and writes the adapted
  tokenizer to ``<run>/adapted/`` with its before/after scores.  It reuses the ``cluster``
  stage's families when that stage ran, and clusters the defaults itself otherwise.
"""

from __future__ import annotations

import json
from typing import Any

from vqtouch.core import StageJob, StageUnavailable
from vqtouch.core.checkpoint import is_pretrained
from vqtouch.plugins.runtime.run_dir import MissingCheckpointError
from vqtouch.plugins.evaluation.contact import VERDICT_EVIDENCE
from vqtouch.plugins.tokenizer import experiment_metrics, load_tokenizer, reconstruct_all

from .adapt import AdaptSettings
from .stages_plugin import AdaptSection, ClusterSection  # noqa: F401 - re-exported

#: Where the stages write inside a run.
CLUSTER_FOLDER, ADAPTED_FOLDER = "cluster", "adapted"


def _family_tokenizer(job: StageJob) -> tuple[Any, Any]:
    """The tokenizer the section's ``family_tokenizer`` names (see its description) and its checkpoint folder."""

    spec = job.section.family_tokenizer
    try:
        return load_tokenizer(spec or job.run, job.host)
    except MissingCheckpointError as exc:
        where = spec or "this run"
        raise StageUnavailable(
            f"no trained tokenizer in {where} ({exc}); run the tokenizer stage first or set "
            f"{job.stage}.family_tokenizer"
        ) from None


def _tokenizer_note(job: StageJob) -> dict[str, Any]:
    """The tokenizer a stage used, when it is not the run's own (for the result and its caption)."""
    spec = job.section.family_tokenizer
    return {"family_tokenizer": spec} if spec else {}


def _caption(job: StageJob, caption: str) -> str:
    """``caption``, first saying which tokenizer the stage used when it is not the run's own."""
    spec = job.section.family_tokenizer
    if not spec:
        return caption
    kind = "the bundled tokenizer" if is_pretrained(spec) else "the tokenizer"
    return f"With {kind} {spec}, not this run's. {caption}"


def target_spec(job: StageJob) -> str:
    """The experiment's ``target_sensor`` as a sensor spec (the JSON a clustering records as its source)."""
    config = job.assembly.sensor_config("target")
    return json.dumps({"name": config.name, **config.model_dump(mode="json", exclude_defaults=True)}, sort_keys=True)


def run_cluster_stage(job: StageJob) -> dict[str, Any]:
    """Group the section's sensors into families; assign and score the target sensor when there is one."""

    from .families import family_sensor_specs, fit_families, save_families, sensor_images

    section, config = job.section, job.config
    tokenizer, folder = _family_tokenizer(job)
    image_size = tokenizer.autoencoder.vqtouch_spec.context.image_size
    target = target_spec(job) if config.target_sensor is not None else None
    specs = (
        section.sensors if section.sensors is not None else family_sensor_specs(job.host, section.variants_per_family)
    )
    specs = [spec for spec in specs if spec != target]  # the unseen sensor is assigned, not clustered
    families = fit_families(
        tokenizer,
        specs,
        job.host,
        clusterer=job.assembly.component("cluster.clusterer"),
        images=section.images_per_sensor,
        image_size=image_size,
        features=section.features,
        refine_steps=section.refine_steps,
        keep=section.keep,
        seed=config.seed,
        tokenizer_source=str(folder),
        report=lambda line: None,
    )
    result: dict[str, Any] = {
        "sensors": len(specs),
        "families": len(families.summary["families"]),
        "members": "; ".join(", ".join(members) for members in families.summary["families"]),
        **_tokenizer_note(job),
    }
    uncertain = families.summary.get("family_count", {}).get("uncertain")
    if uncertain:
        result["family_count_note"] = uncertain
    extra: dict[str, Any] = {}
    plotted = []
    if target is not None:
        sensor = sensor_images(
            target, job.host, count=section.images_per_sensor, image_size=image_size, seed=config.seed + 1
        )
        assigned, shown = families.unseen(tokenizer, sensor.name, sensor.images, section.threshold)
        plotted.append(shown)
        extra["assignments"] = {sensor.name: {"source": target, **assigned}}
        result |= {
            "target": sensor.name,
            "target_family": "refused" if assigned["refused"] else assigned["family"],
            "margin": assigned["margin"],
            **experiment_metrics(job, reconstruct_all(tokenizer, sensor.images), sensor.images, "zero_shot_"),
        }
    save_families(families, job.run.path / CLUSTER_FOLDER, job.host, extra, plotted)
    job.publish("families", CLUSTER_FOLDER, count=result["families"], tokenizer=str(folder))
    return {
        **result,
        "picture": f"{CLUSTER_FOLDER}/families.png",
        "caption": _caption(
            job,
            "2-D PCA of the tokenizer's image features: each sensor's images (small "
            "points) and prototype (large marker, coloured by family); the unseen target "
            "sensor is a black star labelled with the family it was assigned to.",
        ),
    }


def run_adapt_stage(job: StageJob) -> dict[str, Any]:
    """Adapt the run's tokenizer to the target sensor (see the module docstring)."""
    from .adapt import adapt_tokenizer
    from .adapt_families import families_to_adapt_from

    section, config = job.section, job.config
    tokenizer, folder = _family_tokenizer(job)
    target = target_spec(job)
    clustered = job.run.products().get("families")  # the cluster stage's, when it ran in this run
    families = families_to_adapt_from(
        tokenizer,
        folder,
        job.host,
        families=clustered.path if clustered is not None else None,
        where="the cluster stage's families",
        exclude=target,
        seed=config.seed,
    )
    settings = AdaptSettings(
        shots=section.shots,
        ratio=section.ratio,
        steps=section.steps,
        learning_rate=section.learning_rate,
        eval_images=section.eval_images,
        threshold=section.threshold,
        family=section.family,
        seed=config.seed,
        rebase=section.rebase,
    )
    summary = adapt_tokenizer(
        folder if job.section.family_tokenizer else job.run,
        target,
        families,
        job.host,
        job.run.path / ADAPTED_FOLDER,
        settings,
        overwrite=True,
        report=lambda line: None,
    )
    job.publish(
        "adapted_tokenizer", ADAPTED_FOLDER, target=summary["target"], family=summary["family"], shots=summary["shots"]
    )
    result = {
        "target": summary["target"],
        "family": summary["family"],
        "shots": summary["shots"],
        "ratio": summary["ratio"],
        "steps": summary["steps"],
        "seconds": summary["seconds"],
        **_tokenizer_note(job),
    }
    # The adapted tokenizer's scores, each beside the family tokenizer's before adaptation (before_*) and
    # the sensor's no-contact background (background_*), on the whole image and the contact region.
    after, before = summary["after"], summary["before"]
    scores = ("ssim", "psnr", "contact_psnr", "contact_ssim")
    result |= {key: after[key] for key in scores if key in after}
    result |= {f"before_{key}": before[key] for key in scores if key in before}
    result |= {f"background_{key}": after[f"background_{key}"] for key in scores if f"background_{key}" in after}
    result |= {key: after[key] for key in ("contact_fraction", *VERDICT_EVIDENCE) if key in after}
    result["background"] = summary["background"]
    if "real_frames" in summary:
        real = summary["real_frames"]
        result |= {
            f"{when}real_frames_{key}": real[moment][key]
            for when, moment in (("", "after"), ("before_", "before"))
            for key in ("ssim", "psnr")
        }
    return {
        **result,
        "picture": f"{ADAPTED_FOLDER}/before_after.png",
        "caption": _caption(
            job,
            "Held-out images of the target sensor (top row), the family tokenizer's "
            "reconstructions before adaptation (middle row) and after (bottom row).",
        ),
    }

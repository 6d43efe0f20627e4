"""The ``tokenizer`` and ``reconstruct`` stages.

- ``tokenizer`` trains the configured autoencoder + quantizer (+ discriminator) on the
  experiment's data with the tokenizer objective, then scores the held-out split with the
  experiment's metrics (``eval.json``, ``reconstructions.png``).
- ``reconstruct`` runs the run's latest trained tokenizer on the real reference frames that
  the experiment's sensor family declares (``real_frames.png``).
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import torch

from vqtouch.core import StageJob, StageUnavailable
from vqtouch.plugins.evaluation.metric_set import MetricSet
from vqtouch.plugins.utils.seeding import resolve_device
from vqtouch.plugins.utils.splits import experiment_split
from vqtouch.core.errors import NothingToEvaluateError
from vqtouch.core.image_size import image_hw
from vqtouch.plugins.utils.images import image_grid, save_png
from vqtouch.plugins.runtime.run_dir import MissingCheckpointError
from vqtouch.plugins.training.trainer import NeverTrainsWarning, Trainer
from vqtouch.plugins.evaluation.contact import (
    VERDICT_EVIDENCE,
    contact_region_scores,
    dataset_background,
    no_contact_image,
)
from vqtouch.plugins.evaluation.directions import shown_scores

from .loading import TOKENIZER_FILES, load_tokenizer, reconstruct_all
from .training import Tokenizer, adversarial_never_trains, evaluate_reconstruction, tokenizer_task


def printable(scores: dict[str, Any]) -> dict[str, Any]:
    """Scores rounded for people and JSON (the example images left out)."""
    return {
        key: (round(value, 4) if isinstance(value, float) else value)
        for key, value in scores.items()
        if key != "examples"
    }


def save_pairs(originals: torch.Tensor, reconstructions: torch.Tensor, path: Path, count: int = 8) -> Path:
    """A picture of the first ``count`` originals (top row) above their reconstructions."""
    count = min(count, len(originals))
    return save_png(image_grid(torch.cat([originals[:count], reconstructions[:count]]), columns=count), path)


def train_tokenizer(job: StageJob) -> dict[str, Any]:
    """Train the configured tokenizer in ``job.run`` and evaluate it on the held-out split."""
    config, section, assembly = job.config, job.section, job.assembly
    device = resolve_device(config.device)
    dataset = assembly.component("data.dataset")
    train_set, val_set = experiment_split(dataset, config.data, config.seed)
    tokenizer = Tokenizer(assembly.component("tokenizer.autoencoder"), assembly.component("tokenizer.quantizer"))
    discriminator = None
    if section.discriminator is not None and section.loss.adversarial_weight > 0:
        discriminator = assembly.component("tokenizer.discriminator")
    never = adversarial_never_trains(section)
    if never is not None:
        warnings.warn(never, NeverTrainsWarning, stacklevel=2)
    task = tokenizer_task(tokenizer, section.loss, device, discriminator)
    trainer = Trainer(
        task,
        train_set,
        section.train,
        batch_size=config.data.batch_size,
        seed=config.seed,
        device=device,
        checkpoint_dir=job.run.checkpoints,
        run=job.run,
        num_workers=config.data.num_workers,
        host=job.host,
        stage=job.stage,
        val_dataset=val_set,
    )
    if job.resume:
        job.run.resume(trainer, job.host, required_files=TOKENIZER_FILES)
    state = trainer.fit()
    metrics = dict(zip((item.name for item in config.metrics), assembly.build_slots(["metrics"]).get("metrics", [])))
    background, background_source = dataset_background(train_set, image_hw(config.data.image_size))
    try:
        scores = evaluate_reconstruction(
            tokenizer, val_set, metrics, device=device, batch_size=config.data.batch_size, background_3HW=background
        )
    except NothingToEvaluateError:  # data.val_fraction=0 holds nothing out: keep the training, say why
        scores = {"evaluation": f"skipped: no held-out samples (data.val_fraction={config.data.val_fraction:g})"}
    if trainer.dist.is_main:
        job.publish("tokenizer", trainer.last_checkpoint, step=state.step)
        if "examples" in scores:
            save_pairs(*scores["examples"], job.run.path / "reconstructions.png")
        best = {"best_step": state.best_step, "best_val_loss": state.best_score} if trainer.validates() else {}
        job.run.write_json(
            "eval.json",
            {
                "step": state.step,
                "trained_in": trainer.precision,  # tokenizer.train.precision with auto resolved for this machine
                "skipped_steps": state.skipped_steps,
                **best,
                "train_samples": len(train_set),
                "val_samples": len(val_set),
                "split_unit": val_set.split_unit,
                "background": background_source,
                **printable(scores),
            },
        )
    return scores


#: The tokenizer stage's scores shown in the run report (eval.json holds them all).
SHOWN_SCORES = (
    "ssim",
    "background_ssim",
    "psnr",
    "background_psnr",
    "ms_ssim",
    "background_ms_ssim",
    "lpips",
    "background_lpips",
    "contact_psnr",
    "background_contact_psnr",
    "contact_fraction",
    "codebook_usage",
    "samples",
    "evaluation",
    "skipped",
    *VERDICT_EVIDENCE,
)


def run_tokenizer_stage(job: StageJob) -> dict[str, Any]:
    """The ``tokenizer`` stage: train, then the held-out scores for the report."""
    scores = printable(train_tokenizer(job))
    return {
        "steps": job.section.train.steps,
        **shown_scores(scores, SHOWN_SCORES, [metric.name for metric in job.config.metrics]),
        **(
            {}
            if "evaluation" in scores
            else {
                "picture": "reconstructions.png",
                "caption": "Held-out images (top row) above the trained tokenizer's reconstructions of them "
                "(bottom row).",
            }
        ),
    }


def run_reconstruct_stage(job: StageJob) -> dict[str, Any]:
    """The ``reconstruct`` stage: the run's tokenizer on the sensor family's real reference frames."""
    try:
        tokenizer, folder = load_tokenizer(job.run, job.host)
    except MissingCheckpointError as exc:
        # Only a missing checkpoint makes the stage unavailable; a wrong one is a failure.
        raise StageUnavailable(f"no trained tokenizer in this run ({exc}); run the tokenizer stage first") from None
    sensor_config = job.assembly.sensor_config("source")
    sensor = job.assembly.sensor("source")
    image_size = tokenizer.autoencoder.vqtouch_spec.context.image_size
    frames = sensor.reference_frames(*image_hw(image_size))
    if frames is None:
        raise StageUnavailable(
            f"sensor family {sensor_config.name!r} declares no real reference frames "
            "(SensorFamily.reference_frames) to reconstruct"
        )
    reconstructions = reconstruct_all(tokenizer, frames)
    background = no_contact_image(sensor, frames)
    scores: dict[str, Any] = {
        "source": f"{len(frames)} real {sensor.sensor_id or sensor_config.name} frames",
        "checkpoint": folder.name,
        **experiment_metrics(job, reconstructions, frames),
        **experiment_metrics(job, background, frames, prefix="background_"),
        **contact_region_scores({"": reconstructions, "background_": background}, frames, background),
    }
    save_pairs(frames, reconstructions, job.run.path / "real_frames.png")
    return {
        **scores,
        "picture": "real_frames.png",
        "caption": f"The first {min(8, len(frames))} of the sensor's real reference frames (top row) above the "
        "tokenizer's reconstructions of them (bottom row).",
    }


def experiment_metrics(
    job: StageJob, predicted_B3HW: torch.Tensor, truth_B3HW: torch.Tensor, prefix: str = ""
) -> dict[str, float]:
    """The experiment's ``metrics`` of ``predicted_B3HW`` against ``truth_B3HW``, by name (``prefix`` + name),
    and ``"skipped"`` with the reason of each that cannot run here."""
    metrics = MetricSet(
        zip((item.name for item in job.config.metrics), job.assembly.build_slots(["metrics"]).get("metrics", []))
    )
    return metrics.score(predicted_B3HW, truth_B3HW, prefix)

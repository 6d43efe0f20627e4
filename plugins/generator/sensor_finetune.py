"""Fine-tuning a family's generator to draw an unseen sensor: :func:`fine_tune_for_sensor`.

The family generator learned its conditions (label, visual, text, touch) on the family's data.  An
unseen sensor brings a few images (the shots) and no conditions.  The generator is fine-tuned on
the codes, under the sensor's adapted tokenizer, of ``ratio`` family training samples per shot
(their conditions as they are, sensor 0) and of the shots (sensor 1, every condition null), with a
**sensor tag** (the ``sensor`` conditioner, ``generator.sensor_tag``) added to every condition:
the family rows keep teaching what each condition draws, the shots teach the new sensor's
appearance, and sampling asks for the condition with sensor 1's tag.  The tag starts at zero, so
fine-tuning begins from exactly the family generator.

The result is an ordinary generator run (``config.json``, ``checkpoints/generator/step-*``, its
``generator`` product pinned to the adapted tokenizer): ``vqtouch generate``, ``load_pipeline`` and
``evaluate generation`` read it as any other, drawing sensor ``generator.sample_sensor`` (1).
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any, Sequence

import torch

from vqtouch.core import Assembly, ConfigError, PluginHost, validate_experiment
from vqtouch.plugins.utils.seeding import resolve_device
from vqtouch.plugins.runtime.run_dir import RunDir
from vqtouch.plugins.utils.splits import DatasetSubset, experiment_split
from vqtouch.core.image_size import image_hw
from vqtouch.plugins.training.trainer import Trainer
from vqtouch.plugins.evaluation.contact import dataset_background
from vqtouch.plugins.tokenizer import TOKENIZER_FILES, load_tokenizer, tokenizer_digest

from .codes import canonical_background, encode_dataset
from .pipeline import load_pipeline
from .stage import CHECKPOINT_FOLDER
from .training import SENSOR_TAG_MODULE, CodesDataset, GeneratorTask, absent_key

#: Sensor indices of a fine-tuned generator's tag: the family's data, the unseen sensor's shots.
FAMILY_SENSOR, NEW_SENSOR = 0, 1


def recorded_tokenizer(tokenizer_folder: Path, out: Path) -> str:
    """How the fine-tuned run records its tokenizer: relative to the run when the two sit side by side
    (``vqtouch fewshot``'s ``tokenizer/`` and ``generator/``, which then move together), else absolute."""
    tokenizer_folder, out = tokenizer_folder.resolve(), out.resolve()
    if tokenizer_folder.is_relative_to(out.parent):
        return os.path.relpath(tokenizer_folder, out)
    return str(tokenizer_folder)


def family_sample_indices(train_indices: Sequence[int], count: int, seed: int) -> list[int]:
    """``count`` of the family's training samples (at most all), a seeded draw kept in dataset order."""
    order = torch.randperm(len(train_indices), generator=torch.Generator().manual_seed(seed + 4242)).tolist()
    return sorted(train_indices[i] for i in order[: min(count, len(train_indices))])


def _placeholder(values: Any, count: int) -> Any:
    """``count`` stand-ins for a condition the shots lack, shaped like the family's ``values`` (they are
    encoded, then replaced: the rows train with the null condition)."""
    if isinstance(values, torch.Tensor):
        return torch.zeros((count, *values.shape[1:]), dtype=values.dtype)
    return [values[0] if values else ""] * count


def mixed_codes(
    family: CodesDataset, shots_codes_NHW: torch.Tensor, keys: Sequence[str], sensor_key: str
) -> CodesDataset:
    """The family rows (sensor 0, their conditions) followed by the shots (sensor 1, every condition
    marked absent), as one :class:`CodesDataset`."""
    count, shots = len(family), len(shots_codes_NHW)
    entries: dict[str, Any] = {}
    for key in keys:
        values = family.entries[key]
        stand_in = _placeholder(values, shots)
        entries[key] = torch.cat([values, stand_in]) if isinstance(values, torch.Tensor) else list(values) + stand_in
        entries[absent_key(key)] = torch.cat(
            [torch.zeros(count, dtype=torch.bool), torch.ones(shots, dtype=torch.bool)]
        )
    entries[sensor_key] = torch.cat(
        [torch.full((count,), FAMILY_SENSOR, dtype=torch.long), torch.full((shots,), NEW_SENSOR, dtype=torch.long)]
    )
    return CodesDataset(torch.cat([family.codes_NHW, shots_codes_NHW]), entries, family.class_names)


def fine_tune_for_sensor(
    family_run: str | Path,
    tokenizer_folder: Path,
    shots_N3HW: torch.Tensor,
    new_background_3HW: torch.Tensor,
    out: Path,
    host: PluginHost,
    *,
    ratio: float,
    steps: int,
    seed: int,
    sensor_names: tuple[str, str],
    learning_rate: float | None = None,
    overwrite: bool = False,
    argv: Sequence[str] | None = None,
    report: Any = print,
) -> dict[str, Any]:
    """Fine-tune ``family_run``'s generator (a run, or a bundle ``pretrained:NAME``, whose recorded config
    says what its data were) for the unseen sensor whose ``shots_N3HW`` were adapted into
    ``tokenizer_folder`` (see the module docstring); writes a generator run into ``out`` and returns
    what was done (sample counts, canonical backgrounds, steps, seconds)."""
    if ratio < 0 or not len(shots_N3HW):
        raise ConfigError(f"ratio must be >= 0 and there must be shots (got ratio {ratio}, {len(shots_N3HW)} shots)")
    family = load_pipeline(family_run, host=host, device="cpu")
    if family.sensor_tag is not None:
        raise ConfigError(f"{family_run}: already a sensor-tagged (few-shot) generator; start from the family's run")
    config = family.config
    section = config.generator
    device = resolve_device(config.device)
    tokenizer = _adapted_tokenizer(tokenizer_folder, family, host, device)
    family_data, shots_codes, keys, backgrounds = _encoded_rows(
        family, tokenizer, shots_N3HW, new_background_3HW, host, ratio=ratio, seed=seed, device=device, report=report
    )
    sensor_tag = _sensor_tag(family, host, sensor_names)
    data = mixed_codes(family_data, shots_codes, keys, sensor_tag.sample_key)
    train_config = _fine_tune_section(section.train, steps, learning_rate)
    tokenizer_at = recorded_tokenizer(Path(tokenizer_folder), Path(out))
    tuned = _tuned_config(config, sensor_tag, tokenizer_at, train_config, host)
    reads = _family_reads(family, family_run)
    run = RunDir.create(tuned, argv=argv, host=host, path=out, overwrite=overwrite, reads=reads)
    try:
        task = _tagged_task(family, seed, sensor_tag)
        report(
            f"fine-tune: {len(family_data)} family samples + {len(shots_codes)} shots (ratio {ratio:g}), "
            f"{steps} steps from the family generator ({family.settings['weights']} weights)"
        )
        state, seconds = _fit_and_publish(
            run, task, data, train_config, config.data.batch_size, seed, device, host, tokenizer_at, tokenizer_folder
        )
        summary = {
            "family_run": str(family_run),
            "family_samples": len(family_data),
            "shots": len(shots_codes),
            "ratio": ratio,
            "steps": state.step,
            "seconds": round(seconds, 1),
            "started_from": f"{family.checkpoint} ({family.settings['weights']} weights)",
            "canonical_background": backgrounds,
            "sensor_tag": {"module": SENSOR_TAG_MODULE, "sensors": list(sensor_names), "samples": NEW_SENSOR},
            # As the run records it: relative when the two move together (a staged fewshot output).
            "tokenizer": tokenizer_at,
            "tokenizer_files": list(TOKENIZER_FILES),
        }
        run.write_json("fewshot_finetune.json", summary)
    finally:
        run.close()
    return summary


def _sensor_tag(family: Any, host: PluginHost, sensor_names: tuple[str, str]) -> Any:
    """The two-sensor tag conditioner (the family's data, the unseen sensor's shots), built in the family's context."""
    return host.build(
        "conditioner",
        {"name": "sensor", "num_sensors": 2, "sensor_names": list(sensor_names)},
        family.conditioners[0].vqtouch_spec.context,
    )


def _family_reads(family: Any, family_run: str | Path) -> list[tuple[str, str, Path]]:
    """What the fine-tuned run reads of the family run (nothing of a bundle)."""
    # The fewshot stage writes its outputs beside them, inside the run.
    return (
        []
        if family.run is None
        else [("--run", "family run", Path(family_run) / n) for n in ("checkpoints", "config.json")]
    )


def _tagged_task(family: Any, seed: int, sensor_tag: Any) -> GeneratorTask:
    """The family generator's training task, every condition offset by its row's sensor tag."""
    train = family.config.generator.train
    return GeneratorTask(
        family.generator,
        family.conditioners,
        train.condition_dropout,
        seed,
        train.conditioner_weights,
        sensor_tag=sensor_tag,
    )


def _adapted_tokenizer(tokenizer_folder: Path, family: Any, host: PluginHost, device: torch.device) -> Any:
    """The adapted tokenizer in ``tokenizer_folder``, refused unless its codebook is the family generator's."""
    tokenizer, _ = load_tokenizer(tokenizer_folder, host, device=str(device))
    if tokenizer.quantizer.codebook_size != getattr(family.generator, "num_codes", tokenizer.quantizer.codebook_size):
        raise ConfigError(
            f"{tokenizer_folder}: its codebook is not the family generator's; adapt the family's tokenizer"
        )
    return tokenizer


def _encoded_rows(
    family: Any,
    tokenizer: Any,
    shots_N3HW: torch.Tensor,
    new_background_3HW: torch.Tensor,
    host: PluginHost,
    *,
    ratio: float,
    seed: int,
    device: torch.device,
    report: Any,
) -> tuple[CodesDataset, torch.Tensor, list[str], dict[str, Any]]:
    """The family rows' and the shots' codes under the adapted tokenizer, the condition keys, the backgrounds note."""
    config = family.config
    report(f"fine-tune: reading the family's data ({config.data.dataset.name})")
    dataset = Assembly(config, host).component("data.dataset")
    train, _ = experiment_split(dataset, config.data, config.seed)
    chosen = family_sample_indices(train.indices, round(ratio * len(shots_N3HW)), seed)
    family_subset = DatasetSubset(dataset, chosen)
    keys = list(dict.fromkeys(key for c in family.conditioners for key in c.sample_entries()))
    family_data = _family_rows(tokenizer, dataset, family_subset, train, keys, config.data.batch_size, device)
    shots_codes = _shot_codes(tokenizer, shots_N3HW, device)
    backgrounds: dict[str, Any] = {"applied": False}
    if config.generator.train.canonical_background:
        shots_codes, backgrounds = _canonicalise_rows(
            family_data, family_subset, train, shots_codes, shots_N3HW, new_background_3HW, tokenizer, config
        )
    return family_data, shots_codes, keys, backgrounds


def _family_rows(
    tokenizer: Any,
    dataset: Any,
    family_subset: DatasetSubset,
    train: Any,
    keys: list[str],
    batch_size: int,
    device: torch.device,
) -> CodesDataset:
    """The codes and condition entries of the chosen family samples (no rows when none is chosen)."""
    # With no family sample (ratio 0) one is still read: the shots' stand-in conditions take its types.
    read = family_subset if len(family_subset) else DatasetSubset(dataset, train.indices[:1])
    family_codes = encode_dataset(tokenizer, read, batch_size=batch_size, device=device)
    family_data = CodesDataset.collect(family_codes, read, keys)
    if not len(family_subset):
        family_data = CodesDataset(
            family_codes[:0], {key: values[:0] for key, values in family_data.entries.items()}, family_data.class_names
        )
    return family_data


def _shot_codes(tokenizer: Any, shots_N3HW: torch.Tensor, device: torch.device) -> torch.Tensor:
    """The shots' codes under the adapted tokenizer, encoded 32 at a time."""
    return torch.cat(
        [
            tokenizer.encode_codes(shots_N3HW[start : start + 32].to(device)).cpu().long()
            for start in range(0, len(shots_N3HW), 32)
        ]
    )


def _canonicalise_rows(
    family_data: CodesDataset,
    family_subset: DatasetSubset,
    train: Any,
    shots_codes: torch.Tensor,
    shots_N3HW: torch.Tensor,
    new_background_3HW: torch.Tensor,
    tokenizer: Any,
    config: Any,
) -> tuple[torch.Tensor, dict[str, Any]]:
    """The family rows' codes (in place) and the shots' in canonical-background form; the shots' and what changed."""
    family_background, _ = dataset_background(train, image_hw(config.data.image_size))
    # The contact is found on the images, not on the adapted tokenizer's decoding of their codes.
    family_changed = 0.0
    if len(family_subset) and family_background is not None:
        family_images = torch.stack([family_subset[i]["tactile"] for i in range(len(family_subset))])
        family_data.codes_NHW, family_changed = canonical_background(
            family_data.codes_NHW, tokenizer, family_background, images_N3HW=family_images
        )
    shots_codes, changed = canonical_background(shots_codes, tokenizer, new_background_3HW, images_N3HW=shots_N3HW)
    backgrounds = {
        "applied": True,
        "family_cells_changed": round(family_changed, 4),
        "shots_cells_changed": round(changed, 4),
    }
    return shots_codes, backgrounds


def _fine_tune_section(train: Any, steps: int, learning_rate: float | None) -> Any:
    """The family's training section for ``steps`` of fine-tuning: a short warm-up, one checkpoint at the end."""
    return train.model_copy(
        update={
            "steps": steps,
            "warmup_steps": min(train.warmup_steps, max(1, steps // 10)),
            "checkpoint_every": max(1, steps),
            "keep_best": False,
            **({"learning_rate": learning_rate} if learning_rate is not None else {}),
        }
    )


def _tuned_config(config: Any, sensor_tag: Any, tokenizer_at: str, train_config: Any, host: PluginHost) -> Any:
    """The fine-tuned run's config: the family's, with the sensor tag, the adapted tokenizer and ``train_config``."""
    recorded = config.to_dict()
    recorded["generator"] |= {
        "sensor_tag": sensor_tag.vqtouch_spec.config.model_dump(mode="json"),
        "sample_sensor": NEW_SENSOR,
        "tokenizer_run": tokenizer_at,
        "train": train_config.model_dump(mode="json"),
    }
    return validate_experiment(recorded, host)


def _fit_and_publish(
    run: RunDir,
    task: GeneratorTask,
    data: CodesDataset,
    train_config: Any,
    batch_size: int,
    seed: int,
    device: torch.device,
    host: PluginHost,
    tokenizer_at: str,
    tokenizer_folder: Path,
) -> tuple[Any, float]:
    """Train ``task`` on ``data`` into ``run`` and publish its generator; the final state and the seconds it took."""
    trainer = Trainer(
        task,
        data,
        train_config,
        # A handful of shots mixed 1:1 can hold fewer samples than the family's batch: one batch is then all.
        batch_size=min(batch_size, len(data)),
        seed=seed,
        device=device,
        checkpoint_dir=run.checkpoints / CHECKPOINT_FOLDER,
        run=run,
        host=host,
        stage="generator",
    )
    tic = time.perf_counter()
    state = trainer.fit()
    seconds = time.perf_counter() - tic
    run.publish(
        "generator",
        trainer.last_checkpoint,
        stage="generator",
        step=state.step,
        tokenizer=tokenizer_at,
        tokenizer_sha256=tokenizer_digest(Path(tokenizer_folder)),
    )
    return state, seconds

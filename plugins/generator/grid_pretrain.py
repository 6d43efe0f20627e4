"""Teaching the condition grid where the contact is before the generator trains.

Why: a visual image places its contact only through the generator's diffusion loss, and each
training scene costs diffusion steps, so the generator's hour sees few scenes.  A network whose only
job is the contact's place learns it from many scenes in minutes (docs/generation.md).
:func:`pretrain_condition_grid` trains the grid conditioners, the generator's grid embedding and its
contact head on :meth:`VQDiffusion.contact_loss` alone (which code cells hold the contact), on the
training scenes plus, for a dataset that can render more (:meth:`new_scenes`, the procedural scenes),
newly drawn ones; the generator then trains as before from a grid that already knows the place
(section 24 measures it on the bundle).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import torch

from vqtouch.plugins.utils.progress import progress

from .stage_plugin import GridPretrainConfig


def grid_conditioners(conditioners: Sequence[Any], example: dict[str, Any], chosen: Sequence[int] | None) -> list[int]:
    """The indices of ``conditioners`` the pretraining trains: ``chosen``, each checked to give a grid on
    the one-sample batch ``example``, or every one that does."""
    with_grid = []
    for index, conditioner in enumerate(conditioners):
        with torch.no_grad():
            condition = conditioner(conditioner.condition_of(example))
        if condition.grid_BDhw is not None:
            with_grid.append(index)
    if chosen is None:
        if not with_grid:
            raise ValueError(
                "generator.train.grid_pretrain.steps > 0, but no conditioner gives a condition grid (e.g. "
                "visual_cnn, tactile); add one or set grid_pretrain.steps=0"
            )
        return with_grid
    for index in chosen:
        if index not in with_grid:
            raise ValueError(
                f"generator.train.grid_pretrain.conditioners names {index}, which gives no condition grid "
                f"(those that do: {with_grid or 'none'}); name one of them"
            )
    return list(chosen)


def take(entries: dict[str, Any], index_B: torch.Tensor) -> dict[str, Any]:
    """Rows ``index_B`` of every entry (tensors indexed, lists picked)."""
    return {
        key: values[index_B] if isinstance(values, torch.Tensor) else [values[int(i)] for i in index_B]
        for key, values in entries.items()
    }


def pretrain_condition_grid(
    generator: Any,
    conditioners: Sequence[Any],
    entries: dict[str, Any],
    contact_NHW: torch.Tensor,
    config: GridPretrainConfig,
    chosen: Sequence[int],
    *,
    batch_size: int,
    seed: int,
    device: torch.device | str = "cpu",
) -> dict[str, Any]:
    """Train the conditioners ``chosen`` (:func:`grid_conditioners`), ``generator``'s grid embedding and its
    contact head on the contact loss for ``config.steps`` batches of ``entries`` (every sample entry
    the conditioners read) against ``contact_NHW`` (bool, the contact's code cells); what was done
    (scenes, steps, seconds, the loss at the start and the end) for generation.json.

    A pure function of ``seed`` and the data: the batches and the conditioner of each step come from a
    generator seeded with it."""
    head_params = list(getattr(generator, "contact_parameters", list)())
    if not head_params:
        raise ValueError(
            f"generator.train.grid_pretrain needs a generator with a contact head (vq_diffusion with "
            f"model.contact_weight > 0); this {type(generator).__name__} has none"
        )
    count = len(contact_NHW)
    if count == 0:
        raise ValueError("generator.train.grid_pretrain has no scenes to train on (an empty training split)")
    params = [p for i in chosen for p in conditioners[i].parameters() if p.requires_grad] + head_params
    optimizer = torch.optim.AdamW(params, lr=config.learning_rate, weight_decay=config.weight_decay)
    draws = torch.Generator().manual_seed(seed + 104_729)
    losses: list[float] = []
    started = time.perf_counter()
    for module in (generator, *(conditioners[i] for i in chosen)):
        module.train()
    for step in progress(range(config.steps), desc="grid pretraining", unit="step"):
        conditioner = conditioners[chosen[step % len(chosen)]]
        index_B = torch.randint(count, (batch_size,), generator=draws)
        batch = {
            key: value.to(device) if isinstance(value, torch.Tensor) else value
            for key, value in take(entries, index_B).items()
        }
        loss = generator.contact_loss(conditioner(conditioner.condition_of(batch)), contact_NHW[index_B].to(device))
        if not torch.isfinite(loss):
            raise FloatingPointError(
                f"grid pretraining: the contact loss is {float(loss)} at step {step}; lower "
                f"generator.train.grid_pretrain.learning_rate (now {config.learning_rate})"
            )
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
    window = max(1, min(100, len(losses) // 10))
    return {
        "scenes": count,
        "steps": config.steps,
        "conditioners": chosen,
        "seconds": round(time.perf_counter() - started, 1),
        "contact_bce_first": round(sum(losses[:window]) / window, 4) if losses else None,
        "contact_bce_last": round(sum(losses[-window:]) / window, 4) if losses else None,
    }

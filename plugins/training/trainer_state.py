"""What a checkpoint's ``trainer_state.safetensors`` holds and how it is put back: the optimizer
state flattened into tensors plus JSON, the RNG states, the EMA weights and the
:class:`TrainerState` counters, with the batch size, seed and world size an exact resume needs."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from safetensors import safe_open
from safetensors.torch import save_file
from torch import nn

from vqtouch.core.checkpoint import load_state_strict, write_checkpoint_file
from vqtouch.core.errors import CheckpointError

from .checkpoints import first_line


@dataclass
class TrainerState:
    """Counters that make a resumed run continue exactly."""

    step: int = 0
    skipped_steps: int = 0
    consecutive_skips: int = 0
    history: list[dict[str, float]] = field(default_factory=list)
    #: The checkpoint step with the lowest validation loss so far and that loss (None before any).
    best_step: int | None = None
    best_score: float | None = None


def trainer_tensors(
    optimizers: dict[str, torch.optim.Optimizer],
    ema: dict[str, dict[str, torch.Tensor]],
    state: TrainerState,
    *,
    seed: int,
    batch_size: int,
    world: int,
    modules: list[str],
) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """The trainer state as (tensors, JSON-ready meta): RNG states, optimizer tensors and EMA weights
    by key; optimizer param groups and scalars, the counters and the run's shape in the meta."""
    tensors: dict[str, torch.Tensor] = {"rng.torch_cpu": torch.get_rng_state()}
    if torch.cuda.is_available():
        for index, rng in enumerate(torch.cuda.get_rng_state_all()):
            tensors[f"rng.cuda{index}"] = rng
    optim_meta = {}
    for name, optimizer in optimizers.items():
        state_dict = optimizer.state_dict()
        scalars: dict[str, dict[str, Any]] = {}
        for index, values in state_dict["state"].items():
            for key, value in values.items():
                if isinstance(value, torch.Tensor):
                    tensors[f"optim.{name}.{index}.{key}"] = value.detach().cpu().contiguous()
                else:
                    scalars.setdefault(str(index), {})[key] = value
        optim_meta[name] = {"param_groups": state_dict["param_groups"], "scalars": scalars}
    for module_name, shadow in ema.items():
        for key, value in shadow.items():
            tensors[f"ema.{module_name}.{key}"] = value.detach().cpu().contiguous()
    meta = {
        "step": state.step,
        "skipped_steps": state.skipped_steps,
        "consecutive_skips": state.consecutive_skips,
        "history": state.history,
        "best_step": state.best_step,
        "best_score": state.best_score,
        "optimizers": optim_meta,
        "seed": seed,
        "batch_size": batch_size,
        "world": world,
        # Lets readers check that every module file of the step is there.
        "modules": sorted(modules),
    }
    return tensors, meta


def write_trainer_state(path: Path, tensors: dict[str, torch.Tensor], meta: dict[str, Any]) -> None:
    """Write the trainer state file (see :func:`write_checkpoint_file` for how a failed write reads)."""
    write_checkpoint_file(
        path,
        lambda tmp: save_file(
            tensors,
            str(tmp),
            metadata={
                "format": "pt",
                "vqtouch.format_version": "1",
                "vqtouch.component": "trainer_state",
                "vqtouch.trainer": json.dumps(meta, sort_keys=True),
            },
        ),
    )


def read_trainer_state(path: Path) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """The (meta, tensors) of a trainer state file; CheckpointError when it cannot be read."""
    try:
        with safe_open(str(path), framework="pt") as handle:
            meta = json.loads(handle.metadata()["vqtouch.trainer"])
            tensors = {key: handle.get_tensor(key) for key in handle.keys()}
    except Exception as exc:  # noqa: BLE001
        raise CheckpointError(f"{path}: unreadable trainer state ({first_line(exc)})") from None
    return meta, tensors


def load_module_files(modules: dict[str, nn.Module], folder: Path, device: torch.device) -> None:
    """Load each module's ``<name>.safetensors`` of ``folder`` into it, strictly."""
    from safetensors.torch import load_file

    for name, module in modules.items():
        module_path = folder / f"{name}.safetensors"
        try:
            module_tensors = load_file(str(module_path), device=str(device))
        except Exception as exc:  # noqa: BLE001 - safetensors raises several error types
            raise CheckpointError(f"{module_path}: tensor data is unreadable ({first_line(exc)})") from None
        load_state_strict(module, module_tensors, module_path)


def load_optimizer_states(
    optimizers: dict[str, torch.optim.Optimizer],
    meta: dict[str, Any],
    tensors: dict[str, torch.Tensor],
    device: torch.device,
) -> None:
    """Put every optimizer back in the state :func:`trainer_tensors` flattened."""
    for name, optimizer in optimizers.items():
        saved = meta["optimizers"][name]
        state: dict[int, dict[str, Any]] = {}
        for key, value in tensors.items():
            prefix = f"optim.{name}."
            if key.startswith(prefix):
                index, state_key = key[len(prefix) :].split(".", 1)
                state.setdefault(int(index), {})[state_key] = value.to(device)
        for index, values in saved["scalars"].items():
            state.setdefault(int(index), {}).update(values)
        optimizer.load_state_dict({"state": state, "param_groups": saved["param_groups"]})


def restore_ema_and_rng(
    ema: dict[str, dict[str, torch.Tensor]], tensors: dict[str, torch.Tensor], device: torch.device
) -> None:
    """Put back the EMA weights (in place in ``ema``) and the CPU and CUDA RNG states."""
    for module_name, shadow in ema.items():
        for key in shadow:
            shadow[key] = tensors[f"ema.{module_name}.{key}"].to(device)
    torch.set_rng_state(tensors["rng.torch_cpu"])
    if torch.cuda.is_available():
        cuda_states = [tensors[k] for k in sorted(tensors) if k.startswith("rng.cuda")]
        if cuda_states:
            torch.cuda.set_rng_state_all(cuda_states)


def state_from_meta(meta: dict[str, Any]) -> TrainerState:
    """The counters a trainer state file recorded."""
    return TrainerState(
        meta["step"],
        meta["skipped_steps"],
        meta["consecutive_skips"],
        meta["history"],
        meta.get("best_step"),
        meta.get("best_score"),
    )

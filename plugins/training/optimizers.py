"""The trainer's optimizers: Adam or AdamW over parameter groups with their own learning-rate scale,
with the fused kernel wherever the parameters allow it."""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import nn

from .settings import TrainConfig


def _fused_supported(param_groups: list[dict[str, Any]]) -> bool:
    """Whether Adam's fused kernel takes these parameters: float tensors, every one on the CPU or
    every one on one CUDA device.  The same update as the per-tensor loops in one pass over memory
    (bench/bench_precision.py: the optimizer step 4x faster on this CPU)."""
    tensors = [tensor for group in param_groups for tensor in group["params"]]
    devices = {tensor.device for tensor in tensors}
    return (
        len(devices) == 1
        and next(iter(devices)).type in ("cpu", "cuda")
        and all(tensor.dtype in (torch.float32, torch.float64, torch.bfloat16, torch.float16) for tensor in tensors)
    )


def make_optimizer(
    name: str, params: list[nn.Parameter] | list[dict[str, Any]], config: TrainConfig
) -> torch.optim.Optimizer:
    """Optimizer ``name`` of ``config`` over ``params``: a list of parameters, or of groups
    ``{"params": [...], "lr_scale": x}`` each at ``x`` times the learning rate."""
    kind = torch.optim.AdamW if config.optimizer == "adamw" else torch.optim.Adam
    groups = params if params and isinstance(params[0], dict) else [{"params": list(params)}]
    param_groups = []
    for group in groups:
        unknown = set(group) - {"params", "lr_scale"}
        if unknown:
            raise ValueError(
                f"parameter group of optimizer {name!r} has unknown keys {sorted(unknown)}; "
                "allowed: 'params' and 'lr_scale'"
            )
        scale = float(group.get("lr_scale", 1.0))
        if not (math.isfinite(scale) and scale > 0):
            raise ValueError(f"optimizer {name!r}: lr_scale must be a positive finite number, got {scale}")
        # lr_scale stays in the group (and so in checkpoints) to show why its lr differs.
        param_groups.append({"params": list(group["params"]), "lr": config.learning_rate * scale, "lr_scale": scale})
    return kind(
        param_groups,
        lr=config.learning_rate,
        betas=config.betas,
        weight_decay=config.weight_decay,
        fused=_fused_supported(param_groups) or None,
    )

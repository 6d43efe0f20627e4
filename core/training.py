"""One trainer for every trained component: optimisation, precision, checkpoints, resume.

A *task* (e.g. tokenizer training) owns the models and the losses; the trainer owns
everything else.  The task implements::

    modules: dict[str, nn.Module]             # trained components, checkpointed one file each
    parameter_groups() -> dict[str, list]     # optimizer name -> parameters it updates, or
                                              # param-group dicts {"params": [...], "lr_scale": x}
    training_step(batch, step, trainer) -> dict[str, float]

and calls ``trainer.optimize(name, loss)`` for each optimizer, in the order it wants (a GAN
steps its generator, then its discriminator).  ``optimize`` skips non-finite losses (and
reports them), averages gradients across processes, clips and steps.

Checkpoints go to ``<run>/checkpoints/step-NNNNNNNN/``: one safetensors file per module,
EMA weights when enabled, and ``trainer_state.safetensors`` (optimizer state flattened into
tensors plus JSON, RNG states, step).  The trainer state is written last, so a folder
without it is an interrupted save and is ignored on resume.  Resuming reproduces the run
exactly: the data order is a pure function of (seed, epoch) and every RNG state is restored.

Data parallel: launched under ``torchrun``, each process takes every world_size-th sample of
each batch and gradients are all-reduced (gloo on CPU, nccl on GPU); rank 0 writes files.
"""

from __future__ import annotations

import contextlib
import functools
import json
import math
import os
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol

import torch
from pydantic import Field
from safetensors import safe_open
from safetensors.torch import save_file
from torch import nn

from .checkpoint import atomic_write, load_state_strict, save
from .config import Section
from .errors import CheckpointError, VqtouchError
from .progress import progress

TRAINER_STATE = "trainer_state.safetensors"


class TrainConfig(Section):
    """How the trainer optimises one stage's task.

    Each training stage owns one of these in its own section (``tokenizer.train``, ...) and
    may subclass it to change defaults (VQGAN trains with Adam betas (0.5, 0.9)); these
    defaults are the usual AdamW ones.
    """

    steps: int = Field(1000, ge=0, description="Optimisation steps.")
    learning_rate: float = Field(1e-4, gt=0, le=10, description="Peak learning rate.")
    weight_decay: float = Field(0.0, ge=0, le=1, description="Decoupled weight decay (AdamW).")
    grad_clip: float | None = Field(1.0, gt=0, description="Clip the gradient norm to this value; null disables.")
    precision: Literal["fp32", "bf16"] = Field(
        "fp32", description="Autocast precision of the networks; quantizer and diffusion maths stay fp32.")
    optimizer: Literal["adamw", "adam"] = Field("adamw", description="Optimizer of every trained module.")
    betas: tuple[float, float] = Field((0.9, 0.999), description="Adam betas.")
    ema_decay: float | None = Field(None, gt=0.0, lt=1.0,
                                    description="Keep an exponential moving average of the weights with this decay "
                                                "(saved next to the raw weights); null disables.")
    checkpoint_every: int = Field(500, ge=1, description="Write a checkpoint every this many steps.")
    log_every: int = Field(50, ge=1, description="Write metrics.jsonl every this many steps.")
    max_skipped_steps: int = Field(20, ge=1, description="Abort after this many consecutive steps with a non-finite "
                                                         "loss (each one is skipped and reported).")


class TrainingTask(Protocol):
    """What the trainer drives (see the module docstring)."""

    modules: dict[str, nn.Module]

    def parameter_groups(self) -> dict[str, list[nn.Parameter] | list[dict[str, Any]]]:
        """Optimizer name -> the parameters it updates.

        A list of dicts ``{"params": [...], "lr_scale": x}`` instead gives each subset its own
        learning rate, ``x`` times ``TrainConfig.learning_rate`` (``lr_scale`` defaults to 1).
        """

    def training_step(self, batch: dict[str, Any], step: int, trainer: Trainer) -> dict[str, float]:
        """One optimisation step on ``batch``; returns scalars to log."""


class NonFiniteLossError(VqtouchError):
    """Too many consecutive steps produced NaN or Inf losses."""


def collate_samples(samples: list[dict[str, Any]]) -> dict[str, Any]:
    """Stack tensors and numbers of dataset samples; keep strings as lists."""
    batch: dict[str, Any] = {}
    for key in samples[0]:
        values = [sample[key] for sample in samples]
        if isinstance(values[0], torch.Tensor):
            batch[key] = torch.stack(values)
        elif isinstance(values[0], (int, float)):
            batch[key] = torch.tensor(values)
        else:
            batch[key] = values
    return batch


@functools.lru_cache(maxsize=4)
def epoch_order(seed: int, epoch: int, size: int) -> tuple[int, ...]:
    """The sample order of one epoch: a pure function of (seed, epoch) (cached: every step of an
    epoch asks for it)."""
    return tuple(torch.randperm(size, generator=torch.Generator().manual_seed(seed * 100_003 + epoch)).tolist())


def batch_indices(seed: int, step: int, batch_size: int, size: int, rank: int = 0, world: int = 1) -> list[int]:
    """This process's share of the global batch of ``step`` (global batch = batch_size * world)."""
    global_batch = batch_size * world
    per_epoch = max(1, size // global_batch)
    epoch, position = divmod(step, per_epoch)
    order = epoch_order(seed, epoch, size)
    start = position * global_batch
    return list(order[start:start + global_batch][rank::world])


@dataclass
class DistributedContext:
    """Rank and world size; world 1 when not launched by torchrun."""

    rank: int = 0
    world: int = 1

    @property
    def is_main(self) -> bool:
        """Whether this process writes files and shows progress."""
        return self.rank == 0

    @classmethod
    def from_environment(cls, device: torch.device) -> DistributedContext:
        """Join the process group torchrun set up (WORLD_SIZE > 1), else a single process."""
        world = int(os.environ.get("WORLD_SIZE", "1"))
        if world <= 1:
            return cls()
        import torch.distributed as dist

        if not dist.is_initialized():
            dist.init_process_group(backend="nccl" if device.type == "cuda" else "gloo")
        return cls(dist.get_rank(), dist.get_world_size())


@dataclass
class TrainerState:
    """Counters that make a resumed run continue exactly."""

    step: int = 0
    skipped_steps: int = 0
    consecutive_skips: int = 0
    history: list[dict[str, float]] = field(default_factory=list)


class Trainer:
    """Runs a :class:`TrainingTask` for ``config.steps`` steps (see the module docstring)."""

    def __init__(self, task: TrainingTask, dataset: Any, config: TrainConfig, *, batch_size: int, seed: int,
                 device: torch.device, checkpoint_dir: Path | None, run: Any = None, num_workers: int = 0,
                 host: Any = None, stage: str = "train") -> None:
        self.task = task
        self.dataset = dataset
        self.config = config
        self.batch_size = batch_size
        self.seed = seed
        self.device = device
        self.checkpoint_dir = checkpoint_dir
        self.run = run
        self.num_workers = num_workers
        self.host = host
        #: Written as the "stage" of every metrics.jsonl line (the stage that trains).
        self.stage = stage
        self.dist = DistributedContext.from_environment(device)
        self.state = TrainerState()
        for module in task.modules.values():
            module.to(device)
        self._broadcast_parameters()
        self.optimizers = {name: self._make_optimizer(name, params) for name, params in task.parameter_groups().items()}
        self.ema: dict[str, dict[str, torch.Tensor]] = {}
        if config.ema_decay is not None:
            self.ema = {name: {k: v.detach().clone() for k, v in module.state_dict().items()
                               if v.dtype.is_floating_point} for name, module in task.modules.items()}

    # -- optimisation ---------------------------------------------------------------------
    def _make_optimizer(self, name: str, params: list[nn.Parameter] | list[dict[str, Any]]) -> torch.optim.Optimizer:
        kind = torch.optim.AdamW if self.config.optimizer == "adamw" else torch.optim.Adam
        groups = params if params and isinstance(params[0], dict) else [{"params": list(params)}]
        param_groups = []
        for group in groups:
            unknown = set(group) - {"params", "lr_scale"}
            if unknown:
                raise ValueError(f"parameter group of optimizer {name!r} has unknown keys {sorted(unknown)}; "
                                 "allowed: 'params' and 'lr_scale'")
            scale = float(group.get("lr_scale", 1.0))
            if not (math.isfinite(scale) and scale > 0):
                raise ValueError(f"optimizer {name!r}: lr_scale must be a positive finite number, got {scale}")
            # lr_scale stays in the group (and so in checkpoints) to show why its lr differs.
            param_groups.append({"params": list(group["params"]), "lr": self.config.learning_rate * scale,
                                 "lr_scale": scale})
        return kind(param_groups, lr=self.config.learning_rate, betas=self.config.betas,
                    weight_decay=self.config.weight_decay)

    def autocast(self) -> contextlib.AbstractContextManager:
        """The autocast context of the configured precision (a no-op in fp32)."""
        if self.config.precision == "bf16":
            return torch.autocast(device_type=self.device.type, dtype=torch.bfloat16)
        return contextlib.nullcontext()

    def optimize(self, name: str, loss: torch.Tensor) -> bool:
        """Backward ``loss`` and step optimizer ``name``; returns False when the step was skipped.

        A non-finite loss (or gradient) skips the step for every process alike, so ranks
        never diverge; the skip is counted and logged.
        """
        optimizer = self.optimizers[name]
        params = [p for group in optimizer.param_groups for p in group["params"]]
        finite = torch.isfinite(loss.detach()).all().float().reshape(1)
        if self.dist.world > 1:
            import torch.distributed as dist

            dist.all_reduce(finite, op=dist.ReduceOp.MIN)
        optimizer.zero_grad(set_to_none=True)
        if finite.item() == 1.0:
            loss.backward()
            self._average_gradients(params)
            norm = torch.nn.utils.clip_grad_norm_(params, self.config.grad_clip or math.inf)
            if torch.isfinite(norm):
                optimizer.step()
                optimizer.zero_grad(set_to_none=True)
                return True
        optimizer.zero_grad(set_to_none=True)
        self._step_skipped = True
        return False

    def _average_gradients(self, params: list[nn.Parameter]) -> None:
        if self.dist.world == 1:
            return
        import torch.distributed as dist

        for param in params:
            if param.grad is None:
                param.grad = torch.zeros_like(param)
            dist.all_reduce(param.grad)
            param.grad /= self.dist.world

    def _broadcast_parameters(self) -> None:
        if self.dist.world == 1:
            return
        import torch.distributed as dist

        for module in self.task.modules.values():
            for tensor in module.state_dict().values():
                dist.broadcast(tensor, src=0)

    def _update_ema(self) -> None:
        decay = self.config.ema_decay
        for name, shadow in self.ema.items():
            current = self.task.modules[name].state_dict()
            with torch.no_grad():
                for key, value in shadow.items():
                    value.lerp_(current[key].to(value.dtype), 1 - decay)

    # -- data -------------------------------------------------------------------------------
    def _batches(self, start_step: int) -> Iterator[dict[str, Any]]:
        size = len(self.dataset)
        if size < self.batch_size * self.dist.world:
            raise VqtouchError(f"the dataset has {size} samples, fewer than one global batch "
                               f"({self.batch_size} x {self.dist.world} processes); lower data.batch_size")
        index_batches = [batch_indices(self.seed, step, self.batch_size, size, self.dist.rank, self.dist.world)
                         for step in range(start_step, self.config.steps)]
        # A private generator: creating the iterator would otherwise draw its worker seed from
        # the global RNG, and a resumed run (which creates it at another moment) would diverge.
        loader = torch.utils.data.DataLoader(self.dataset, batch_sampler=index_batches, collate_fn=collate_samples,
                                             num_workers=self.num_workers,
                                             generator=torch.Generator().manual_seed(self.seed + start_step))
        yield from loader

    # -- the loop ---------------------------------------------------------------------------
    def fit(self) -> TrainerState:
        """Train until ``config.steps``; Ctrl-C saves a checkpoint first, then re-raises."""
        start = self.state.step
        bar = progress(total=self.config.steps, initial=start, desc="training", unit="step") if self.dist.is_main \
            else None
        images_seen, tic = 0, time.perf_counter()
        try:
            for batch in self._batches(start):
                step = self.state.step
                batch = {k: v.to(self.device) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}
                self._step_skipped = False
                scalars = self.task.training_step(batch, step, self)
                if self._step_skipped:
                    self.state.skipped_steps += 1
                    self.state.consecutive_skips += 1
                    if self.state.consecutive_skips >= self.config.max_skipped_steps:
                        raise NonFiniteLossError(
                            f"{self.state.consecutive_skips} consecutive steps had a non-finite loss (last at step "
                            f"{step}); lower the stage's train.learning_rate or check the data. The last good "
                            "checkpoint is kept")
                else:
                    self.state.consecutive_skips = 0
                if self.ema:
                    self._update_ema()
                self.state.step = step + 1
                images_seen += self.batch_size * self.dist.world
                scalars = {**scalars, "skipped_steps": float(self.state.skipped_steps)}
                if self.state.step % self.config.log_every == 0 or self.state.step == self.config.steps:
                    self.state.history.append({"step": self.state.step, **scalars})
                    if self.run is not None and self.dist.is_main:
                        self.run.log_metrics(self.stage, self.state.step, scalars)
                if self.state.step % self.config.checkpoint_every == 0:
                    self.save_checkpoint()
                if bar is not None:
                    rate = images_seen / max(time.perf_counter() - tic, 1e-9)
                    bar.set_postfix({k: f"{v:.4g}" for k, v in list(scalars.items())[:3]} | {"img/s": f"{rate:.1f}"},
                                    refresh=False)
                    bar.update(1)
        except KeyboardInterrupt:
            self.save_checkpoint()
            raise
        finally:
            if bar is not None:
                bar.close()
        if self.state.step % self.config.checkpoint_every != 0:
            self.save_checkpoint()
        return self.state

    # -- checkpoints -------------------------------------------------------------------------
    def save_checkpoint(self) -> Path | None:
        """Write modules, EMA weights and trainer state for the current step (rank 0 only)."""
        if self.checkpoint_dir is None or not self.dist.is_main:
            return None
        folder = self.checkpoint_dir / f"step-{self.state.step:08d}"
        folder.mkdir(parents=True, exist_ok=True)
        for name, module in self.task.modules.items():
            save(module, folder / f"{name}.safetensors", step=self.state.step, host=self.host)
        tensors, meta = self._trainer_tensors()
        atomic_write(folder / TRAINER_STATE,
                     lambda tmp: save_file(tensors, str(tmp), metadata={
                         "format": "pt", "vqtouch.format_version": "1", "vqtouch.component": "trainer_state",
                         "vqtouch.trainer": json.dumps(meta, sort_keys=True)}))
        return folder

    def _trainer_tensors(self) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
        tensors: dict[str, torch.Tensor] = {"rng.torch_cpu": torch.get_rng_state()}
        if torch.cuda.is_available():
            for index, state in enumerate(torch.cuda.get_rng_state_all()):
                tensors[f"rng.cuda{index}"] = state
        optim_meta = {}
        for name, optimizer in self.optimizers.items():
            state_dict = optimizer.state_dict()
            scalars: dict[str, dict[str, Any]] = {}
            for index, values in state_dict["state"].items():
                for key, value in values.items():
                    if isinstance(value, torch.Tensor):
                        tensors[f"optim.{name}.{index}.{key}"] = value.detach().cpu().contiguous()
                    else:
                        scalars.setdefault(str(index), {})[key] = value
            optim_meta[name] = {"param_groups": state_dict["param_groups"], "scalars": scalars}
        for module_name, shadow in self.ema.items():
            for key, value in shadow.items():
                tensors[f"ema.{module_name}.{key}"] = value.detach().cpu().contiguous()
        meta = {"step": self.state.step, "skipped_steps": self.state.skipped_steps,
                "consecutive_skips": self.state.consecutive_skips, "history": self.state.history,
                "optimizers": optim_meta, "seed": self.seed, "batch_size": self.batch_size, "world": self.dist.world}
        return tensors, meta

    def resume(self, checkpoint_dir: Path) -> bool:
        """Load the latest complete checkpoint under ``checkpoint_dir``; False when there is none."""
        folder = latest_checkpoint(checkpoint_dir)
        if folder is None:
            return False
        path = folder / TRAINER_STATE
        try:
            with safe_open(str(path), framework="pt") as handle:
                meta = json.loads(handle.metadata()["vqtouch.trainer"])
                tensors = {key: handle.get_tensor(key) for key in handle.keys()}
        except Exception as exc:  # noqa: BLE001
            raise CheckpointError(f"{path}: unreadable trainer state ({exc})") from None
        if meta["batch_size"] != self.batch_size or meta["seed"] != self.seed or meta["world"] != self.dist.world:
            raise CheckpointError(f"{path}: saved with batch_size={meta['batch_size']}, seed={meta['seed']}, "
                                  f"world={meta['world']}; resuming needs the same values to continue exactly")
        from safetensors.torch import load_file

        for name, module in self.task.modules.items():
            load_state_strict(module, load_file(str(folder / f"{name}.safetensors"), device=str(self.device)),
                              folder / f"{name}.safetensors")
        for name, optimizer in self.optimizers.items():
            saved = meta["optimizers"][name]
            state: dict[int, dict[str, Any]] = {}
            for key, value in tensors.items():
                prefix = f"optim.{name}."
                if key.startswith(prefix):
                    index, state_key = key[len(prefix):].split(".", 1)
                    state.setdefault(int(index), {})[state_key] = value.to(self.device)
            for index, values in saved["scalars"].items():
                state.setdefault(int(index), {}).update(values)
            optimizer.load_state_dict({"state": state, "param_groups": saved["param_groups"]})
        for module_name, shadow in self.ema.items():
            for key in shadow:
                shadow[key] = tensors[f"ema.{module_name}.{key}"].to(self.device)
        torch.set_rng_state(tensors["rng.torch_cpu"])
        if torch.cuda.is_available():
            cuda_states = [tensors[k] for k in sorted(tensors) if k.startswith("rng.cuda")]
            if cuda_states:
                torch.cuda.set_rng_state_all(cuda_states)
        self.state = TrainerState(meta["step"], meta["skipped_steps"], meta["consecutive_skips"], meta["history"])
        return True


def latest_checkpoint(checkpoint_dir: Path) -> Path | None:
    """The newest ``step-*`` folder that holds a complete trainer state, or None."""
    if not checkpoint_dir.is_dir():
        return None
    complete = sorted(p for p in checkpoint_dir.glob("step-*") if (p / TRAINER_STATE).is_file())
    return complete[-1] if complete else None

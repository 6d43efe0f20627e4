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
tensors plus JSON, RNG states, step, the module names).  The trainer state is written last,
so a folder without it is an interrupted save.  The newest complete, readable folder is the
one source of truth (:func:`latest_good_checkpoint`; there is no ``latest`` pointer file):
newer folders that are incomplete or damaged are skipped with a warning.  Only the newest
``keep_last`` complete folders are kept, plus the one with the best held-out score when the
task can score one (``validation_loss``, ``keep_best``).  Resuming reproduces the run exactly: the data order
is a pure function of (seed, epoch) and every RNG state is restored; the run's metrics.jsonl
loses the lines of the steps after the resumed one, which are logged again.

Stopping: during :meth:`Trainer.fit`, Ctrl-C (SIGINT) and SIGTERM (what schedulers send)
finish the current step, write its checkpoint and raise :class:`TrainingInterrupted` (a
KeyboardInterrupt).  More signals while that happens only print a note: a checkpoint being
written is always finished (kill -9 still stops at once; the atomic writes keep the last
complete checkpoint intact).

Data parallel: launched under ``torchrun``, each process takes every world_size-th sample of
each batch and gradients are all-reduced (gloo on CPU, nccl on GPU); rank 0 writes files.
"""

from __future__ import annotations

import contextlib
import math
import shutil
import signal
import time
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import torch
from torch import nn

from vqtouch.core.checkpoint import (
    TRAINED_IN_KEY,
    CheckpointWriteError,
    remove_stale_temporaries,
    save,
)
from .settings import TrainConfig, learning_rate_factor
from vqtouch.core.errors import CheckpointError, VqtouchError, VqtouchWarning
from vqtouch.plugins.utils.progress import progress

from .checkpoints import (
    TRAINER_STATE,
    STEP_FOLDER,
    checkpoint_problem,
    latest_checkpoint,
    latest_good_checkpoint,
    no_good_checkpoint,
    rewind_metrics,
    step_folders,
)
from .batches import StepBatches, collate_samples
from .optimizers import make_optimizer
from .trainer_state import (
    TrainerState,
    load_module_files,
    load_optimizer_states,
    read_trainer_state,
    restore_ema_and_rng,
    state_from_meta,
    trainer_tensors,
    write_trainer_state,
)
from .processes import DistributedContext, StopSignals
from .precision import autocast, resolve_precision

if TYPE_CHECKING:
    from vqtouch.core.plugin_manager import PluginHost


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

    # Optional: ``validation_loss(batch, trainer) -> torch.Tensor`` (B,), the per-sample held-out
    # score, lower is better; with it (and a validation set) the trainer keeps the best checkpoint.


class NonFiniteLossError(VqtouchError):
    """Too many consecutive steps produced NaN or Inf losses."""


class TrainingInterrupted(KeyboardInterrupt):
    """Ctrl-C or SIGTERM stopped :meth:`Trainer.fit`; the checkpoint of the step reached is complete.

    A KeyboardInterrupt, so callers that catch Ctrl-C keep working.  ``checkpoint`` is the
    folder written (None without a checkpoint folder, and on ranks other than 0).
    """

    def __init__(self, cause: str, step: int, checkpoint: Path | None) -> None:
        saved = f"checkpoint saved: {checkpoint}" if checkpoint is not None else "no checkpoint written by this process"
        super().__init__(f"training stopped by {cause} after step {step}; {saved}")
        self.cause, self.step, self.checkpoint = cause, step, checkpoint


class NeverTrainsWarning(VqtouchWarning):
    """A configured term or schedule never takes effect in this run (it starts after the last step)."""


class Trainer:
    """Runs a :class:`TrainingTask` for ``config.steps`` steps (see the module docstring)."""

    def __init__(
        self,
        task: TrainingTask,
        dataset: Any,
        config: TrainConfig,
        *,
        batch_size: int,
        seed: int,
        device: torch.device,
        checkpoint_dir: Path | None,
        run: Any = None,
        num_workers: int = 0,
        host: PluginHost | None = None,
        stage: str = "train",
        val_dataset: Any = None,
    ) -> None:
        self.task = task
        self.dataset = dataset
        #: Held-out samples scored at every checkpoint (``keep_best``); None or empty: no scoring.
        self.val_dataset = val_dataset
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
        #: The precision the networks run in: ``config.precision`` with ``auto`` resolved for ``device``.
        self.precision = resolve_precision(config.precision, device, config.component)
        if 0 < config.steps < config.warmup_steps:
            key = f"{config.component}.train" if config.component else "train"
            warnings.warn(
                f"{key}.warmup_steps={config.warmup_steps} is longer than the run ({key}.steps={config.steps}): "
                "the learning rate never reaches its peak; lower warmup_steps or raise steps",
                NeverTrainsWarning,
                stacklevel=2,
            )
        self.state = TrainerState()
        #: The step whose checkpoint folder is known complete (saved or resumed from), so an
        #: interrupt right after a save does not write it twice.
        self._saved: tuple[int, Path] | None = None
        self._signals: StopSignals | None = None
        #: Set when another rank's stop request ended :meth:`fit` (see :meth:`_stop_agreed`).
        self._stopped_by_peer = False
        if checkpoint_dir is not None and self.dist.is_main:
            # A new trainer is the only writer of its run's checkpoints: whatever temporaries are
            # there were left by a killed save (full-size weights, never cleaned otherwise).
            remove_stale_temporaries(checkpoint_dir)
            for _, folder in step_folders(checkpoint_dir):
                remove_stale_temporaries(folder, safetensors_temporaries=True)
        for module in task.modules.values():
            module.to(device)
        self._broadcast_parameters()
        self.optimizers = {
            name: make_optimizer(name, params, config) for name, params in task.parameter_groups().items()
        }
        self.ema: dict[str, dict[str, torch.Tensor]] = {}
        if config.ema_decay is not None:
            self.ema = {
                name: {k: v.detach().clone() for k, v in module.state_dict().items() if v.dtype.is_floating_point}
                for name, module in task.modules.items()
            }

    # -- optimisation ---------------------------------------------------------------------
    def autocast(self) -> contextlib.AbstractContextManager:
        """The autocast context of the configured precision (a no-op in fp32; ``auto`` as :func:`resolve_precision`)."""
        return autocast(self.precision, self.device)

    def optimize(self, name: str, loss: torch.Tensor) -> bool:
        """Backward ``loss`` and step optimizer ``name``; returns False when the step was skipped.

        A non-finite loss (or gradient) skips the step for every process alike, so ranks
        never diverge; the skip is counted and logged.
        """
        optimizer = self.optimizers[name]
        factor = learning_rate_factor(self.config, self.state.step)
        for group in optimizer.param_groups:
            group["lr"] = self.config.learning_rate * group.get("lr_scale", 1.0) * factor
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

    def _update_ema(self, updates: int) -> None:
        """Fold the current weights into the average; ``updates``: how many steps it holds after this one."""
        decay = self.config.ema_decay
        if self.config.ema_unbiased:
            # The decay that keeps the shadow equal to sum_k decay**(n-k) w_k / sum_k decay**(n-k):
            # 0 at the first update (the shadow becomes the first trained weights), -> decay later.
            decay = decay * (1 - decay ** (updates - 1)) / (1 - decay**updates)
        for name, shadow in self.ema.items():
            current = self.task.modules[name].state_dict()
            with torch.no_grad():
                for key, value in shadow.items():
                    value.lerp_(current[key].to(value.dtype), 1 - decay)

    # -- data -------------------------------------------------------------------------------
    def _batches(self, start_step: int) -> Iterator[dict[str, Any]]:
        size = len(self.dataset)
        if size < self.batch_size * self.dist.world:
            raise VqtouchError(
                f"the dataset has {size} samples, fewer than one global batch "
                f"({self.batch_size} x {self.dist.world} processes); lower data.batch_size"
            )
        index_batches = StepBatches(
            self.seed, start_step, self.config.steps, self.batch_size, size, self.dist.rank, self.dist.world
        )
        # A private generator: creating the iterator would otherwise draw its worker seed from
        # the global RNG, and a resumed run (which creates it at another moment) would diverge.
        loader = torch.utils.data.DataLoader(
            self.dataset,
            batch_sampler=index_batches,
            collate_fn=collate_samples,
            num_workers=self.num_workers,
            generator=torch.Generator().manual_seed(self.seed + start_step),
        )
        yield from loader

    # -- the loop ---------------------------------------------------------------------------
    def fit(self) -> TrainerState:
        """Train until ``config.steps``, writing checkpoints on the way and at the end.

        Ctrl-C or SIGTERM finishes the current step, writes its checkpoint and raises
        :class:`TrainingInterrupted`; further signals meanwhile do not abort that save.  A
        KeyboardInterrupt raised by the task itself also saves first.  The previous signal
        handlers are back in place when fit returns or raises.
        """
        signals = StopSignals().install()
        self._signals = signals
        self._stopped_by_peer = False
        interrupted: KeyboardInterrupt | None = None
        try:
            try:
                self._run_steps(signals)
            except KeyboardInterrupt as exc:  # raised by the task, or by a handler other than ours
                interrupted = exc
            stopped = interrupted is not None or signals.received is not None or self._stopped_by_peer
            # A fit of no steps (steps=0, e.g. only a stage's pretraining) still leaves its weights.
            if stopped or self.state.step % self.config.checkpoint_every != 0 or self._saved is None:
                self._save_unless_saved()
        finally:
            self._signals = None
            signals.restore()
        # Checked after the last save too: a signal during it still stops the caller.
        if interrupted is not None or signals.received is not None or self._stopped_by_peer:
            if signals.received is not None:
                cause = signal.Signals(signals.received).name
            else:
                cause = "a stop request to another process" if self._stopped_by_peer else "KeyboardInterrupt"
            folder = self._saved[1] if self._saved is not None and self._saved[0] == self.state.step else None
            raise TrainingInterrupted(cause, self.state.step, folder) from interrupted
        return self.state

    def _run_steps(self, signals: StopSignals) -> None:
        start = self.state.step
        bar = (
            progress(total=self.config.steps, initial=start, desc=f"training ({self.precision})", unit="step")
            if self.dist.is_main
            else None
        )
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
                            "checkpoint is kept"
                        )
                else:
                    self.state.consecutive_skips = 0
                if self.ema:
                    self._update_ema(step + 1)
                self.state.step = step + 1
                images_seen += self.batch_size * self.dist.world
                scalars = {**scalars, "skipped_steps": float(self.state.skipped_steps)}
                # The first and the last step always: a run shorter than log_every still draws its curve.
                if self.state.step in (1, self.config.steps) or self.state.step % self.config.log_every == 0:
                    self.state.history.append({"step": self.state.step, **scalars})
                    if self.run is not None and self.dist.is_main:
                        self.run.log_metrics(self.stage, self.state.step, scalars)
                if self.state.step % self.config.checkpoint_every == 0:
                    self.save_checkpoint()
                if bar is not None:
                    rate = images_seen / max(time.perf_counter() - tic, 1e-9)
                    bar.set_postfix(
                        {k: f"{v:.4g}" for k, v in list(scalars.items())[:3]} | {"img/s": f"{rate:.1f}"}, refresh=False
                    )
                    bar.update(1)
                if self._stop_agreed(signals):
                    break
        finally:
            if bar is not None:
                bar.close()

    def _stop_agreed(self, signals: StopSignals) -> bool:
        """Whether to stop after this step: a stop request to any process stops them all at the same
        step (under torchrun a signal may reach one rank only, or reach the ranks a step apart,
        and a rank that stopped alone would leave the others waiting in their next all-reduce)."""
        stop = signals.received is not None
        if self.dist.world > 1:
            import torch.distributed as dist

            flag = torch.tensor([1.0 if stop else 0.0], device=self.device)
            dist.all_reduce(flag, op=dist.ReduceOp.MAX)
            if flag.item() > 0 and not stop:
                self._stopped_by_peer = True
                stop = True
        return stop

    # -- checkpoints -------------------------------------------------------------------------
    def save_checkpoint(self) -> Path | None:
        """Write modules, EMA weights and trainer state for the current step (rank 0 only), then
        delete complete checkpoints older than the newest ``config.keep_last``.

        SIGINT/SIGTERM arriving meanwhile wait until the folder is complete.  A failed write
        raises a one-line CheckpointError naming the file and the cause; the folder being
        written is removed and the earlier checkpoints are untouched.
        """
        if self.checkpoint_dir is None or not self.dist.is_main:
            return None
        if self._signals is not None:  # inside fit: its handlers defer, fit stops afterwards
            self._signals.saving = True
            try:
                return self._write_checkpoint()
            finally:
                self._signals.saving = False
        deferred = StopSignals().install()
        deferred.saving = True
        try:
            return self._write_checkpoint()
        finally:
            deferred.restore()
            if deferred.received is not None:
                signal.raise_signal(deferred.received)  # now to the handler it was meant for

    @property
    def last_checkpoint(self) -> Path | None:
        """The step folder this trainer last wrote or resumed from (None before either): after
        :meth:`fit`, the finished model's, which a stage publishes as its product."""
        return self._saved[1] if self._saved is not None else None

    def _save_unless_saved(self) -> Path | None:
        if self._saved is not None and self._saved[0] == self.state.step and self._saved[1].is_dir():
            return self._saved[1]
        return self.save_checkpoint()

    def _write_checkpoint(self) -> Path:
        step = self.state.step
        self._validate(step)
        folder = self.checkpoint_dir / f"step-{step:08d}"
        created = not folder.exists()
        try:
            try:
                folder.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise CheckpointError(
                    f"{folder}: cannot create the checkpoint folder ({exc.strerror or exc}); make "
                    f"{self.checkpoint_dir} writable"
                ) from None
            for name, module in self.task.modules.items():
                trained_in = {TRAINED_IN_KEY: self.precision}  # what `auto` resolved to, for readers of the run
                save(module, folder / f"{name}.safetensors", step=step, host=self.host, metadata=trained_in)
            tensors, meta = self._trainer_tensors()
            # Written last: its presence is what makes the folder a complete checkpoint.
            write_trainer_state(folder / TRAINER_STATE, tensors, meta)
        except BaseException as exc:
            if created:
                shutil.rmtree(folder, ignore_errors=True)  # only this save's files: an incomplete step
            if isinstance(exc, CheckpointWriteError):
                previous = latest_checkpoint(self.checkpoint_dir)
                kept = (
                    f"nothing was replaced; the run's last complete checkpoint is {previous.name}"
                    if previous is not None
                    else "nothing was replaced; the run has no complete checkpoint yet"
                )
                raise exc.keeping(kept) from None
            raise
        self._saved = (step, folder)
        self._remove_old_checkpoints(step)
        return folder

    def validates(self) -> bool:
        """Whether checkpoints are scored on held-out samples (and the best one kept)."""
        return (
            self.config.keep_best
            and hasattr(self.task, "validation_loss")
            and self.val_dataset is not None
            and len(self.val_dataset) > 0
        )

    @torch.no_grad()
    def _validate(self, step: int) -> None:
        """Score the held-out split at ``step`` (val_loss in metrics.jsonl) and remember the best step.

        Runs once per checkpoint, on rank 0; the RNG states are put back afterwards, so scoring
        changes neither the training that follows nor an exact resume.
        """
        if not self.validates():
            return
        cpu_state = torch.get_rng_state()
        cuda_states = torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None
        training = {name: module.training for name, module in self.task.modules.items()}
        total, count = 0.0, 0
        try:
            for start in range(0, len(self.val_dataset), self.batch_size):
                samples = [
                    self.val_dataset[i] for i in range(start, min(start + self.batch_size, len(self.val_dataset)))
                ]
                batch = {
                    k: v.to(self.device) if isinstance(v, torch.Tensor) else v
                    for k, v in collate_samples(samples).items()
                }
                losses_B = self.task.validation_loss(batch, self)
                total += float(losses_B.double().sum())
                count += len(samples)
        finally:
            for name, module in self.task.modules.items():
                module.train(training[name])
            torch.set_rng_state(cpu_state)
            if cuda_states is not None:
                torch.cuda.set_rng_state_all(cuda_states)
        score = total / count
        if self.run is not None:
            self.run.log_metrics(self.stage, step, {"val_loss": score})
        # A non-finite score is logged but never "best": NaN compares False with everything.
        if math.isfinite(score) and (self.state.best_score is None or score < self.state.best_score):
            self.state.best_step, self.state.best_score = step, score

    def _remove_old_checkpoints(self, step: int) -> None:
        # Only complete folders older than the one just written count; newer ones (left by a run
        # that was resumed from an earlier step) are overwritten when training reaches them.  The
        # best-scoring folder is kept apart from the keep_last newest.
        older = [
            folder
            for number, folder in step_folders(self.checkpoint_dir)
            if number < step and number != self.state.best_step and (folder / TRAINER_STATE).is_file()
        ]
        for folder in older[: max(0, len(older) - (self.config.keep_last - 1))]:
            try:
                # The trainer state first: a deletion cut short leaves an incomplete folder, never
                # one that looks complete but lacks a module file.
                (folder / TRAINER_STATE).unlink()
                shutil.rmtree(folder)
            except OSError as exc:
                warnings.warn(
                    f"could not delete the old checkpoint {folder} ({exc.strerror or exc}); delete it by "
                    "hand to free its space",
                    stacklevel=3,
                )

    def _trainer_tensors(self) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
        return trainer_tensors(
            self.optimizers,
            self.ema,
            self.state,
            seed=self.seed,
            batch_size=self.batch_size,
            world=self.dist.world,
            modules=list(self.task.modules),
        )

    def resume(self, checkpoint_dir: Path) -> bool:
        """Load the newest good checkpoint under ``checkpoint_dir`` (or the step folder given);
        False when the run has no checkpoint folder at all.

        Newer folders that are incomplete or unreadable are skipped with a
        :class:`SkippedCheckpointWarning`.  A ``checkpoints/`` folder that holds step folders but
        no good one raises CheckpointError rather than starting over.  The run's metrics.jsonl
        loses this stage's lines after the resumed step (they are logged again).
        """
        checkpoint_dir = Path(checkpoint_dir)
        required = [f"{name}.safetensors" for name in self.task.modules]
        if STEP_FOLDER.fullmatch(checkpoint_dir.name) and checkpoint_dir.is_dir():
            folder = checkpoint_dir
            problem = checkpoint_problem(folder, required)
            if problem is not None:
                raise CheckpointError(f"{folder}: cannot resume from it: {problem}; choose another step folder")
        else:
            folder = latest_good_checkpoint(checkpoint_dir, required_files=required)
            if folder is None:
                if step_folders(checkpoint_dir):
                    raise CheckpointError(
                        f"{no_good_checkpoint(checkpoint_dir, required)}; resuming would silently "
                        f"restart from step 0: delete {checkpoint_dir} to start over"
                    )
                self._rewind_run_metrics(0)
                return False
        path = folder / TRAINER_STATE
        meta, tensors = read_trainer_state(path)
        if meta["batch_size"] != self.batch_size or meta["seed"] != self.seed or meta["world"] != self.dist.world:
            raise CheckpointError(
                f"{path}: saved with batch_size={meta['batch_size']}, seed={meta['seed']}, "
                f"world={meta['world']}; resuming needs the same values to continue exactly"
            )
        load_module_files(self.task.modules, folder, self.device)
        load_optimizer_states(self.optimizers, meta, tensors, self.device)
        restore_ema_and_rng(self.ema, tensors, self.device)
        self.state = state_from_meta(meta)
        self._saved = (self.state.step, folder)
        self._rewind_run_metrics(self.state.step)
        return True

    def _rewind_run_metrics(self, step: int) -> None:
        path = getattr(self.run, "path", None)
        if path is not None and self.dist.is_main:
            rewind_metrics(Path(path) / "metrics.jsonl", self.stage, step)

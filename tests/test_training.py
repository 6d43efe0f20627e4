"""The generic trainer: exact resume, Ctrl-C, non-finite steps, EMA, bf16, data parallel."""

import os
import subprocess
import sys
from pathlib import Path
from typing import ClassVar, Literal

import pytest
import torch
from safetensors.torch import load_file
from torch import nn

from vqtouch.core import BuildContext, Conditioner, PluginConfig, hookimpl, load_plugins
from vqtouch.plugins.training.settings import TrainConfig
from vqtouch.plugins.training.checkpoints import TRAINER_STATE, SkippedCheckpointWarning, latest_checkpoint
from vqtouch.plugins.training.trainer import NonFiniteLossError, Trainer
from vqtouch.plugins.training.batches import batch_indices


class ToyDataset:
    """y = 3x - 1 with noise; x in the 'tactile' slot to look like a real sample."""

    def __init__(self, size: int = 40) -> None:
        generator = torch.Generator().manual_seed(0)
        self.x = torch.randn(size, 4, generator=generator)
        self.y = self.x @ torch.tensor([3.0, -1.0, 0.5, 2.0]) - 1

    def __len__(self) -> int:
        return len(self.x)

    def __getitem__(self, index: int):
        return {"tactile": self.x[index], "label": float(self.y[index])}


class RegressorConfig(PluginConfig):
    name: Literal["toy_regressor"] = "toy_regressor"


class Regressor(Conditioner):
    """A trainable module built through the host, so checkpoints can record how to rebuild it."""

    def __init__(self) -> None:
        super().__init__(cond_dim=1, num_tokens=1)
        self.linear = nn.Linear(4, 1)
        self.dropout = nn.Dropout(0.2)  # consumes the global RNG: resume must restore it

    def encode(self, condition):
        return self.linear(self.dropout(condition)).view(-1, 1, 1)


@hookimpl
def vqtouch_register_conditioners(register):
    register("toy_regressor", lambda config, context: Regressor(), RegressorConfig)


class ToyTask:
    def __init__(self, host, poison_steps=(), interrupt_at=None, bias_lr_scale=None):
        self.modules = {"model": host.build("conditioner", "toy_regressor", BuildContext())}
        self.poison_steps = set(poison_steps)
        self.interrupt_at = interrupt_at
        self.bias_lr_scale = bias_lr_scale
        self.losses = []

    def parameter_groups(self):
        linear = self.modules["model"].linear
        if self.bias_lr_scale is not None:
            return {"main": [{"params": [linear.weight]}, {"params": [linear.bias], "lr_scale": self.bias_lr_scale}]}
        return {"main": list(self.modules["model"].parameters())}

    def training_step(self, batch, step, trainer):
        if step == self.interrupt_at:
            raise KeyboardInterrupt
        with trainer.autocast():
            prediction = self.modules["model"].encode(batch["tactile"]).view(-1)
        self.prediction_dtype = prediction.dtype
        loss = (prediction.float() - batch["label"].float()).pow(2).mean()
        if step in self.poison_steps:
            loss = loss * float("nan")
        trainer.optimize("main", loss)
        self.losses.append(float(loss.detach()))
        return {"loss": float(loss.detach())}


@pytest.fixture
def host(make_plugin):
    return load_plugins(autoload=False, extra=[make_plugin("toy", vqtouch_register_conditioners)])


def make_trainer(host, tmp_path, steps=12, task_options=None, **config):
    torch.manual_seed(0)  # same initial weights for every trainer a test makes
    task = ToyTask(host, **(task_options or {}))
    options = {"steps": steps, "learning_rate": 0.05, "checkpoint_every": 4, "log_every": 1, **config}
    return Trainer(
        task,
        ToyDataset(),
        TrainConfig(**options),
        batch_size=4,
        seed=3,
        device=torch.device("cpu"),
        checkpoint_dir=tmp_path / "checkpoints",
        host=host,
    ), task


def test_training_reduces_the_loss_and_writes_checkpoints(host, tmp_path):
    trainer, task = make_trainer(host, tmp_path, steps=40)
    trainer.fit()
    assert task.losses[-1] < task.losses[0] / 5
    assert latest_checkpoint(tmp_path / "checkpoints").name == "step-00000040"
    # The newest complete step-* folder is the one source of truth: no pointer file to fall out of date;
    # the newest keep_last (3) are kept.
    assert sorted(p.name for p in (tmp_path / "checkpoints").iterdir()) == [
        f"step-{step:08d}" for step in range(32, 41, 4)
    ]
    assert {p.name for p in (tmp_path / "checkpoints" / "step-00000040").iterdir()} == {
        "model.safetensors",
        "trainer_state.safetensors",
    }


def test_a_fit_of_no_steps_leaves_the_untrained_weights_as_its_checkpoint(host, tmp_path):
    """steps=0 (a stage that only pretrains, or only scores) still has a product to publish."""
    trainer, task = make_trainer(host, tmp_path, steps=0)
    trainer.fit()
    assert trainer.last_checkpoint == tmp_path / "checkpoints" / "step-00000000"
    saved = load_file(trainer.last_checkpoint / "model.safetensors")
    assert saved and all(torch.equal(saved[k], v) for k, v in task.modules["model"].state_dict().items())
    assert task.losses == []


def test_resume_reproduces_the_uninterrupted_run_exactly(host, tmp_path):
    full, full_task = make_trainer(host, tmp_path / "full")
    full.fit()
    first, first_task = make_trainer(host, tmp_path / "split", task_options={"interrupt_at": 6})
    with pytest.raises(KeyboardInterrupt):
        first.fit()  # Ctrl-C at step 6: a checkpoint of step 6 is written first
    assert latest_checkpoint(tmp_path / "split" / "checkpoints").name == "step-00000006"
    torch.manual_seed(12345)  # whatever happened in between must not matter
    second, second_task = make_trainer(host, tmp_path / "split")
    assert second.resume(tmp_path / "split" / "checkpoints") and second.state.step == 6
    second.fit()
    assert first_task.losses + second_task.losses == full_task.losses
    for a, b in zip(full.task.modules["model"].parameters(), second.task.modules["model"].parameters()):
        assert torch.equal(a, b)


def test_a_resumed_run_continues_the_unbiased_ema_exactly(host, tmp_path):
    """The EMA's bias correction counts updates from the run's step, so an interrupted run resumed from
    its checkpoint ends with the same average as the uninterrupted one."""
    full, _ = make_trainer(host, tmp_path / "full", ema_decay=0.9)
    full.fit()
    first, _ = make_trainer(host, tmp_path / "split", task_options={"interrupt_at": 6}, ema_decay=0.9)
    with pytest.raises(KeyboardInterrupt):
        first.fit()
    second, _ = make_trainer(host, tmp_path / "split", ema_decay=0.9)
    assert second.resume(tmp_path / "split" / "checkpoints") and second.state.step == 6
    second.fit()
    assert torch.equal(second.ema["model"]["linear.weight"], full.ema["model"]["linear.weight"])


def test_lr_scale_gives_a_parameter_group_its_own_learning_rate(host, tmp_path):
    trainer, _ = make_trainer(host, tmp_path, steps=1, task_options={"bias_lr_scale": 0.1}, grad_clip=None)
    weight_groups = trainer.optimizers["main"].param_groups
    assert [g["lr"] for g in weight_groups] == pytest.approx([0.05, 0.005])
    linear = trainer.task.modules["model"].linear
    before = linear.weight.detach().clone(), linear.bias.detach().clone()
    trainer.fit()
    # Adam's first step moves every parameter with a non-zero gradient by lr * g/(|g| + eps) ~ lr.
    assert (linear.weight - before[0]).abs().flatten().tolist() == pytest.approx([0.05] * 4, rel=1e-3)
    assert (linear.bias - before[1]).abs().item() == pytest.approx(0.005, rel=1e-3)


def test_resume_keeps_scaled_learning_rates(host, tmp_path):
    first, _ = make_trainer(host, tmp_path, steps=4, task_options={"bias_lr_scale": 0.1})
    first.fit()
    second, _ = make_trainer(host, tmp_path, steps=8, task_options={"bias_lr_scale": 0.1})
    assert second.resume(tmp_path / "checkpoints")
    assert [g["lr"] for g in second.optimizers["main"].param_groups] == pytest.approx([0.05, 0.005])


def test_bad_parameter_groups_are_refused(host, tmp_path):
    task = ToyTask(host)
    task.parameter_groups = lambda: {"main": [{"params": list(task.modules["model"].parameters()), "lr": 1.0}]}
    with pytest.raises(ValueError, match="unknown keys \\['lr'\\].*'lr_scale'"):
        Trainer(
            task,
            ToyDataset(),
            TrainConfig(steps=1),
            batch_size=4,
            seed=0,
            device=torch.device("cpu"),
            checkpoint_dir=None,
        )
    task.parameter_groups = lambda: {"main": [{"params": list(task.modules["model"].parameters()), "lr_scale": 0}]}
    with pytest.raises(ValueError, match="lr_scale must be a positive finite number"):
        Trainer(
            task,
            ToyDataset(),
            TrainConfig(steps=1),
            batch_size=4,
            seed=0,
            device=torch.device("cpu"),
            checkpoint_dir=None,
        )


def test_resume_without_checkpoint_returns_false(host, tmp_path):
    trainer, _ = make_trainer(host, tmp_path)
    assert trainer.resume(tmp_path / "nothing") is False


def test_incomplete_checkpoint_folder_is_ignored(host, tmp_path):
    trainer, _ = make_trainer(host, tmp_path, steps=8)
    trainer.fit()
    checkpoints = tmp_path / "checkpoints"
    (checkpoints / "step-00000099").mkdir()  # a save that died before writing anything
    # A save that died after the module files but before its trainer state (written last).
    newer = checkpoints / "step-00000012"
    newer.mkdir()
    (newer / "model.safetensors").write_bytes((checkpoints / "step-00000008" / "model.safetensors").read_bytes())
    assert latest_checkpoint(checkpoints).name == "step-00000008"
    resumed, _ = make_trainer(host, tmp_path, steps=12)
    with pytest.warns(SkippedCheckpointWarning) as caught:
        assert resumed.resume(checkpoints) and resumed.state.step == 8
    assert [str(w.message) for w in caught] == [
        f"checkpoint {checkpoints / name} skipped: no {TRAINER_STATE}: its save was interrupted"
        for name in ("step-00000099", "step-00000012")
    ]
    # Once the newer folder is complete, it is the latest.
    (newer / TRAINER_STATE).write_bytes((checkpoints / "step-00000008" / TRAINER_STATE).read_bytes())
    assert latest_checkpoint(checkpoints).name == "step-00000012"
    assert latest_checkpoint(tmp_path / "no-such-folder") is None


def test_train_config_defaults_are_generic_and_stages_subclass_them(host, tmp_path):
    from vqtouch.core import resolve_config

    assert TrainConfig().betas == (0.9, 0.999) and TrainConfig().optimizer == "adamw"
    trainer, _ = make_trainer(host, tmp_path, steps=1)
    assert trainer.optimizers["main"].defaults["betas"] == (0.9, 0.999)
    trainer, _ = make_trainer(host, tmp_path, steps=1, betas=(0.5, 0.9))
    assert trainer.optimizers["main"].defaults["betas"] == (0.5, 0.9)
    # The tokenizer stage owns its TrainConfig (tokenizer.train.*), with VQGAN's betas.
    config = resolve_config("label-to-touch", overrides=["tokenizer.train.steps=7"], host=load_plugins(autoload=False))
    assert isinstance(config.tokenizer.train, TrainConfig)
    assert config.tokenizer.train.steps == 7 and config.tokenizer.train.betas == (0.5, 0.9)
    assert "train" not in type(config).model_fields


@pytest.mark.parametrize(
    "override, problem",
    [
        ("betas=[2,3]", "betas: each Adam beta must be a number in [0, 1), e.g. [0.9, 0.999] (got [2, 3])"),
        ("betas=[0.9,1.0]", "betas: each Adam beta must be a number in [0, 1), e.g. [0.9, 0.999] (got [0.9, 1.0])"),
        ("betas=[-0.1,0.9]", "betas: each Adam beta must be a number in [0, 1), e.g. [0.9, 0.999] (got [-0.1, 0.9])"),
        ("betas=[0.9,NaN]", "betas: each Adam beta must be a number in [0, 1), e.g. [0.9, 0.999] (got [0.9, nan])"),
        ("betas=[false,0.9]", "betas: each Adam beta must be a number in [0, 1), e.g. [0.9, 0.999] (got [False, 0.9])"),
        ("steps=true", "steps: Input should be a valid integer (got True)"),
        ("steps=2.0", "steps: Input should be a valid integer (got 2.0)"),
        ("steps=100000000", "steps: Input should be less than or equal to 99999999 (got 100000000)"),
        ("checkpoint_every=true", "checkpoint_every: Input should be a valid integer (got True)"),
        ("log_every=false", "log_every: Input should be a valid integer (got False)"),
        ("max_skipped_steps=true", "max_skipped_steps: Input should be a valid integer (got True)"),
        ("keep_last=0", "keep_last: Input should be greater than or equal to 1 (got 0)"),
        ("learning_rate=true", "learning_rate: Input should be a valid number (got True)"),
        ("grad_clip=true", "grad_clip: Input should be a valid number (got True)"),
    ],
)
def test_train_config_refuses_values_that_would_crash_or_mislead_later(override, problem):
    from vqtouch.core import ConfigError, resolve_config

    # tokenizer.train is a subclass with its own betas default: the checks hold for it too.
    with pytest.raises(ConfigError) as info:
        resolve_config("label-to-touch", overrides=[f"tokenizer.train.{override}"], host=load_plugins(autoload=False))
    assert str(info.value) == f"invalid configuration: tokenizer.train.{problem}"


def test_train_config_keeps_accepting_what_is_sensible():
    config = TrainConfig(steps=99_999_999, betas=[0.0, 0.999], learning_rate=1, grad_clip=5, ema_decay=0.999)
    assert config.betas == (0.0, 0.999) and config.learning_rate == 1.0 and config.grad_clip == 5.0


def test_a_long_run_does_not_build_every_batch_up_front(host, tmp_path):
    trainer, task = make_trainer(
        host, tmp_path, steps=99_999_999, checkpoint_every=99_999_999, task_options={"interrupt_at": 3}
    )
    with pytest.raises(KeyboardInterrupt):
        trainer.fit()
    assert len(task.losses) == 3


def test_resume_with_different_batch_size_is_refused(host, tmp_path):
    from vqtouch.core import CheckpointError

    trainer, _ = make_trainer(host, tmp_path, steps=4)
    trainer.fit()
    other = Trainer(
        ToyTask(host),
        ToyDataset(),
        TrainConfig(steps=8),
        batch_size=8,
        seed=3,
        device=torch.device("cpu"),
        checkpoint_dir=tmp_path / "checkpoints",
        host=host,
    )
    with pytest.raises(CheckpointError, match="batch_size=4"):
        other.resume(tmp_path / "checkpoints")


def test_non_finite_loss_skips_the_step_and_is_reported(host, tmp_path):
    trainer, task = make_trainer(host, tmp_path, steps=8, task_options={"poison_steps": {2, 5}})
    state = trainer.fit()
    assert state.skipped_steps == 2
    assert all(torch.isfinite(p).all() for p in task.modules["model"].parameters())
    assert [h["skipped_steps"] for h in state.history][-1] == 2.0


def test_too_many_consecutive_non_finite_steps_abort(host, tmp_path):
    trainer, _ = make_trainer(
        host, tmp_path, steps=30, task_options={"poison_steps": set(range(3, 30))}, max_skipped_steps=5
    )
    with pytest.raises(NonFiniteLossError, match="5 consecutive steps"):
        trainer.fit()


def test_extreme_learning_rate_never_writes_non_finite_weights(host, tmp_path):
    trainer, task = make_trainer(host, tmp_path, steps=30, learning_rate=10.0, grad_clip=None, max_skipped_steps=30)
    try:
        trainer.fit()
    except NonFiniteLossError:
        pass
    assert all(torch.isfinite(p).all() for p in task.modules["model"].parameters())


def test_ema_weights_are_kept_and_saved(host, tmp_path):
    trainer, task = make_trainer(host, tmp_path, steps=8, ema_decay=0.9)
    trainer.fit()
    shadow = trainer.ema["model"]["linear.weight"]
    assert not torch.equal(shadow, task.modules["model"].linear.weight)
    resumed, _ = make_trainer(host, tmp_path, steps=8, ema_decay=0.9)
    resumed.resume(tmp_path / "checkpoints")
    assert torch.equal(resumed.ema["model"]["linear.weight"], shadow)


@pytest.mark.parametrize("unbiased", [True, False])
def test_ema_is_the_decay_weighted_mean_of_the_trained_weights(host, tmp_path, unbiased):
    """The closed form, from the weights recorded after every step: sum_k d**(n-k) w_k over sum_k d**(n-k)
    (unbiased), or the same sum plus d**n times the initial weights (ema_unbiased=false)."""
    decay, steps = 0.9, 12
    trainer, task = make_trainer(host, tmp_path, steps=steps, ema_decay=decay, ema_unbiased=unbiased)
    initial = task.modules["model"].linear.weight.detach().clone()
    trained, step_once = [], task.training_step

    def recording_step(batch, step, trainer):
        scalars = step_once(batch, step, trainer)
        trained.append(task.modules["model"].linear.weight.detach().clone())
        return scalars

    task.training_step = recording_step
    trainer.fit()
    shares = torch.tensor([decay ** (steps - k) for k in range(1, steps + 1)], dtype=torch.float64)
    stacked = torch.stack(trained).double()
    if unbiased:
        expected = (shares[:, None, None] * stacked).sum(0) / shares.sum()
    else:
        expected = (1 - decay) * (shares[:, None, None] * stacked).sum(0) + decay**steps * initial.double()
    assert not torch.allclose(trained[-1].double(), expected, atol=1e-4)  # an average, not the last weights
    torch.testing.assert_close(trainer.ema["model"]["linear.weight"].double(), expected, rtol=0, atol=1e-6)


def test_bf16_autocast_trains(host, tmp_path):
    trainer, task = make_trainer(host, tmp_path, steps=20, precision="bf16")
    trainer.fit()
    assert task.losses[-1] < task.losses[0] and all(torch.isfinite(torch.tensor(task.losses)))


@pytest.mark.parametrize(
    "precision, expected", [("auto", torch.float32), ("fp32", torch.float32), ("bf16", torch.bfloat16)]
)
def test_precision_sets_the_networks_dtype_and_auto_trains_fp32_on_cpu(host, tmp_path, precision, expected):
    """``auto`` (the default) runs a component with no measured choice (the toy task's plain
    TrainConfig) in fp32 on CPU."""
    trainer, task = make_trainer(host, tmp_path, steps=2, **({} if precision == "auto" else {"precision": precision}))
    trainer.fit()
    assert task.prediction_dtype == expected


class _GeneratorLikeConfig(TrainConfig):
    component: ClassVar[str | None] = "generator"


@pytest.mark.parametrize("matrix_units, expected", [(True, "bf16"), (False, "fp32")])
def test_auto_trains_the_generator_in_bf16_only_on_a_cpu_with_bf16_matrix_units(
    host, monkeypatch, recwarn, capsys, matrix_units, expected
):
    """With bf16 matrix units (AMX) ``auto`` trains the generator in bf16; without them it keeps fp32
    and says nothing."""
    from vqtouch.plugins.training import precision as training

    monkeypatch.setattr(training, "cpu_has_bf16_matrix_units", lambda: matrix_units)
    torch.manual_seed(0)
    task = ToyTask(host)
    trainer = Trainer(
        task,
        ToyDataset(),
        _GeneratorLikeConfig(steps=2),
        batch_size=4,
        seed=3,
        device=torch.device("cpu"),
        checkpoint_dir=None,
        host=host,
    )
    trainer.fit()
    dtype = {"bf16": torch.bfloat16, "fp32": torch.float32}[expected]
    assert trainer.precision == expected and task.prediction_dtype == dtype
    assert not [w for w in recwarn if "precision" in str(w.message) or "bf16" in str(w.message)]
    assert "bf16" not in capsys.readouterr().err


def test_auto_precision_per_device_and_component(monkeypatch):
    from vqtouch.plugins.training import precision as training
    from vqtouch.plugins.training.precision import resolve_precision
    from vqtouch.plugins.generator.training import GeneratorTrainConfig
    from vqtouch.plugins.tokenizer.training import TokenizerTrainConfig

    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda *args, **kwargs: True)
    monkeypatch.setattr(training, "cpu_has_bf16_matrix_units", lambda: True)
    generator, tokenizer = GeneratorTrainConfig.component, TokenizerTrainConfig.component
    assert [resolve_precision("auto", torch.device(kind), generator) for kind in ("cpu", "cuda", "meta")] == [
        "bf16",
        "bf16",
        "fp32",
    ]
    for component in (tokenizer, "sampling"):
        assert [resolve_precision("auto", torch.device(kind), component) for kind in ("cpu", "cuda", "meta")] == [
            "bf16",
            "bf16",
            "fp32",
        ]
    # A component without a measured choice keeps fp32 on the CPU.
    assert resolve_precision("auto", torch.device("cpu"), "unmeasured") == "fp32"
    assert resolve_precision("fp32", torch.device("cpu"), generator) == "fp32"  # --set ...precision=fp32 wins
    assert resolve_precision("bf16", torch.device("cpu"), tokenizer) == "bf16"
    monkeypatch.setattr(training, "cpu_has_bf16_matrix_units", lambda: False)
    for component in (generator, tokenizer, "sampling"):
        assert resolve_precision("auto", torch.device("cpu"), component) == "fp32"
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda *args, **kwargs: False)
    assert resolve_precision("auto", torch.device("cuda"), generator) == "fp32"


def test_the_trainer_uses_adams_fused_kernel_on_the_cpu(host, tmp_path):
    trainer, _ = make_trainer(host, tmp_path, steps=1)
    trainer.fit()
    assert [optimizer.defaults["fused"] for optimizer in trainer.optimizers.values()] == [True]


def test_batch_indices_cover_each_epoch_once_and_split_across_ranks():
    size, batch = 20, 5
    epoch = sorted(i for step in range(4) for i in batch_indices(7, step, batch, size))
    assert epoch == list(range(20))
    global_batch = batch_indices(7, 1, 2 * batch, size, 0, 1)
    shares = [batch_indices(7, 1, batch, size, rank, 2) for rank in range(2)]
    assert sorted(shares[0] + shares[1]) == sorted(global_batch)


DDP_SCRIPT = Path(__file__).parent / "helpers" / "ddp_train.py"


def test_two_process_data_parallel_keeps_parameters_identical(tmp_path):
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(Path(__file__).parent / "helpers")}
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "torch.distributed.run",
            "--nproc_per_node",
            "2",
            "--master_port",
            "29517",
            str(DDP_SCRIPT),
            str(tmp_path),
        ],
        capture_output=True,
        text=True,
        timeout=240,
        env=env,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    params = [torch.load(tmp_path / f"rank{rank}.pt", weights_only=True) for rank in range(2)]
    assert torch.equal(params[0], params[1])
    assert not torch.equal(params[0], torch.load(tmp_path / "initial.pt", weights_only=True))


def test_a_signal_to_one_rank_stops_every_rank_at_the_same_step(tmp_path):
    """Under torchrun a rank that stopped alone would leave the others waiting in their next all-reduce."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(Path(__file__).parent / "helpers")}
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "torch.distributed.run",
            "--nproc_per_node",
            "2",
            "--master_port",
            "29519",
            str(DDP_SCRIPT),
            str(tmp_path),
            "signal",
        ],
        capture_output=True,
        text=True,
        timeout=240,
        env=env,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    checkpoint = tmp_path / "checkpoints" / "step-00000004"
    assert (tmp_path / "rank1.stopped").read_text() == "4 SIGTERM None"  # rank 1 writes no file
    assert (tmp_path / "rank0.stopped").read_text() == f"4 a stop request to another process {checkpoint}"
    assert sorted(p.name for p in (tmp_path / "checkpoints").iterdir()) == ["step-00000004"]
    params = [torch.load(tmp_path / f"rank{rank}.pt", weights_only=True) for rank in range(2)]
    assert torch.equal(params[0], params[1])


def test_warm_up_and_cosine_move_each_step_by_the_scheduled_rate(host, tmp_path):
    trainer, _ = make_trainer(
        host,
        tmp_path,
        steps=6,
        task_options={"bias_lr_scale": 0.1},
        grad_clip=None,
        warmup_steps=2,
        lr_schedule="cosine",
        min_lr_ratio=0.2,
    )
    linear = trainer.task.modules["model"].linear
    before = linear.weight.detach().clone()
    trainer.config = trainer.config.model_copy(update={"steps": 1})
    trainer.fit()
    # Adam's first step moves a weight by ~ its learning rate: half the peak at step 0 of a 2-step warm-up.
    assert (linear.weight - before).abs().flatten().tolist() == pytest.approx([0.025] * 4, rel=1e-3)
    assert [g["lr"] for g in trainer.optimizers["main"].param_groups] == pytest.approx([0.025, 0.0025])


def test_a_resumed_run_continues_the_learning_rate_schedule_exactly(host, tmp_path):
    options = {"warmup_steps": 3, "lr_schedule": "cosine"}
    full, full_task = make_trainer(host, tmp_path / "full", **options)
    full.fit()
    first, _ = make_trainer(host, tmp_path / "split", task_options={"interrupt_at": 5}, **options)
    with pytest.raises(KeyboardInterrupt):
        first.fit()
    second, second_task = make_trainer(host, tmp_path / "split", **options)
    assert second.resume(tmp_path / "split" / "checkpoints")
    second.fit()
    for a, b in zip(full.task.modules["model"].parameters(), second.task.modules["model"].parameters()):
        assert torch.equal(a, b)


def test_a_run_shorter_than_log_every_still_logs_its_first_and_last_step(host, tmp_path):
    trainer, _ = make_trainer(host, tmp_path, steps=20, log_every=50, checkpoint_every=50)
    trainer.fit()
    assert [entry["step"] for entry in trainer.state.history] == [1, 20]
    trainer, _ = make_trainer(host, tmp_path / "b", steps=12, log_every=5, checkpoint_every=50)
    trainer.fit()
    assert [entry["step"] for entry in trainer.state.history] == [1, 5, 10, 12]

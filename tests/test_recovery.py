"""Recovering from interruptions: signals during training and saves, damaged newest checkpoints,
full disks, leftovers of interrupted writes, metrics of resumed runs and old checkpoints.

The signal cases send real signals to a training subprocess (the toy task of test_training.py,
each step slowed a little so that the signal lands mid-training)."""

import errno
import importlib.util
import json
import os
import signal
import subprocess
import sys
import time
import types
import warnings
from pathlib import Path

import pytest
import torch

from vqtouch.core import CheckpointError, load_plugins
from vqtouch.plugins.training.settings import TrainConfig
from vqtouch.plugins.runtime.run_dir import RunDir
from vqtouch.plugins.training.checkpoints import (
    TRAINER_STATE,
    SkippedCheckpointWarning,
    latest_checkpoint,
    latest_good_checkpoint,
    no_good_checkpoint,
    rewind_metrics,
)
from vqtouch.plugins.training.trainer import Trainer

TESTS = Path(__file__).resolve().parent


def _load_toy():
    # Test modules cannot import each other under --import-mode=importlib: load it by path.
    spec = importlib.util.spec_from_file_location("recovery_toy_training", TESTS / "test_training.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


toy = _load_toy()


@pytest.fixture
def host():
    plugin = types.ModuleType("toy")
    plugin.vqtouch_register_conditioners = toy.vqtouch_register_conditioners
    return load_plugins(autoload=False, extra=[plugin])


def make_trainer(host, tmp_path, steps=12, run=None, stage="train", **config):
    torch.manual_seed(0)  # the same initial weights as the training subprocess
    task = toy.ToyTask(host)
    options = {"steps": steps, "learning_rate": 0.05, "checkpoint_every": 4, "log_every": 1, **config}
    trainer = Trainer(
        task,
        toy.ToyDataset(),
        TrainConfig(**options),
        batch_size=4,
        seed=3,
        device=torch.device("cpu"),
        checkpoint_dir=tmp_path / "checkpoints",
        host=host,
        run=run,
        stage=stage,
    )
    return trainer, task


def parameters(trainer):
    return [p.detach().clone() for p in trainer.task.modules["model"].parameters()]


# -- signals -------------------------------------------------------------------------------------

TRAIN_SCRIPT = """
import importlib.util, sys, time, types
from pathlib import Path
import torch
from vqtouch.core import load_plugins
from vqtouch.plugins.training.settings import TrainConfig
import vqtouch.plugins.training.trainer as training

spec = importlib.util.spec_from_file_location("toy_training", {test_training!r})
toy = importlib.util.module_from_spec(spec)
spec.loader.exec_module(toy)
plugin = types.ModuleType("toy")
plugin.vqtouch_register_conditioners = toy.vqtouch_register_conditioners
host = load_plugins(autoload=False, extra=[plugin])
out, save_seconds = Path(sys.argv[1]), float(sys.argv[2])


class SlowTask(toy.ToyTask):
    def training_step(self, batch, step, trainer):
        if step == 2:
            (out / "training").touch()
        time.sleep(0.01)
        return super().training_step(batch, step, trainer)


write_module = training.save


def slow_save(module, path, **options):
    (out / "saving").touch()
    time.sleep(save_seconds)  # a big model: the save takes a while
    return write_module(module, path, **options)


training.save = slow_save
torch.manual_seed(0)
trainer = training.Trainer(SlowTask(host), toy.ToyDataset(),
                           TrainConfig(steps=100000, learning_rate=0.05, checkpoint_every=100000, log_every=1),
                           batch_size=4, seed=3, device=torch.device("cpu"), checkpoint_dir=out / "checkpoints",
                           host=host)
try:
    trainer.fit()
except KeyboardInterrupt as exc:
    print(f"caught {{type(exc).__name__}}: {{exc}}", flush=True)
    sys.exit(130)
"""


def start_training(tmp_path, save_seconds):
    script = tmp_path / "train.py"
    script.write_text(TRAIN_SCRIPT.format(test_training=str(TESTS / "test_training.py")))
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    # SIGINT's default action in the child: a suite started in the background (`make test &`) inherits
    # SIGINT ignored, and Python then never turns it into KeyboardInterrupt, so the Ctrl-C tests would hang.
    process = subprocess.Popen(
        [sys.executable, str(script), str(tmp_path), str(save_seconds)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    wait_for(tmp_path / "training", process)
    return process


def wait_for(marker, process, timeout=120.0):
    deadline = time.monotonic() + timeout
    while not marker.exists():
        if process.poll() is not None:
            raise AssertionError(f"training ended early: {process.communicate()}")
        assert time.monotonic() < deadline, f"{marker.name} never appeared"
        time.sleep(0.01)


def finish(process):
    try:
        stdout, stderr = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            process.kill()
    return process.returncode, stdout, stderr


def assert_resumes_exactly(host, tmp_path):
    """The interrupted run's checkpoint is complete and continues exactly like an uninterrupted run."""
    folder = latest_good_checkpoint(tmp_path / "checkpoints")
    assert folder is not None, sorted(str(p.relative_to(tmp_path)) for p in (tmp_path / "checkpoints").rglob("*"))
    step = int(folder.name[5:])
    assert step >= 2
    resumed = make_trainer(host, tmp_path, steps=step + 3, checkpoint_every=1000)[0]
    assert resumed.resume(tmp_path / "checkpoints") and resumed.state.step == step
    resumed.fit()
    full = make_trainer(host, tmp_path / "full", steps=step + 3, checkpoint_every=1000)[0]
    full.fit()
    assert all(torch.equal(a, b) for a, b in zip(parameters(full), parameters(resumed)))
    return step


def test_two_ctrl_c_50_ms_apart_still_save_a_complete_checkpoint(host, tmp_path):
    process = start_training(tmp_path, save_seconds=0.5)
    process.send_signal(signal.SIGINT)
    time.sleep(0.05)
    process.send_signal(signal.SIGINT)  # lands in the (slow) save
    code, stdout, stderr = finish(process)
    assert code == 130, stderr[-3000:]
    step = assert_resumes_exactly(host, tmp_path)
    assert f"caught TrainingInterrupted: training stopped by SIGINT after step {step}; checkpoint saved: " in stdout
    assert "Traceback" not in stderr


def test_a_second_signal_during_the_save_waits_for_it(host, tmp_path):
    process = start_training(tmp_path, save_seconds=1.0)
    process.send_signal(signal.SIGINT)
    wait_for(tmp_path / "saving", process)
    process.send_signal(signal.SIGINT)
    code, stdout, stderr = finish(process)
    assert code == 130, stderr[-3000:]
    assert_resumes_exactly(host, tmp_path)
    notices = [line for line in stderr.splitlines() if line.startswith("vqtouch:")]
    assert notices == [
        "vqtouch: SIGINT received; stopping after the current step, once its checkpoint is written",
        "vqtouch: SIGINT received while writing a checkpoint; stopping once it is complete (kill -9 stops at "
        "once, keeping the last complete checkpoint)",
    ], stderr[-3000:]


def test_sigterm_saves_a_checkpoint_like_ctrl_c(host, tmp_path):
    process = start_training(tmp_path, save_seconds=0.0)
    process.send_signal(signal.SIGTERM)
    code, stdout, stderr = finish(process)
    assert code == 130, (code, stderr[-3000:])
    step = assert_resumes_exactly(host, tmp_path)
    assert f"training stopped by SIGTERM after step {step}; checkpoint saved: " in stdout


def test_fit_handles_sigterm_only_while_it_runs(host, tmp_path):
    def previous_handler(signum, frame):
        raise AssertionError("not during fit")

    trainer, task = make_trainer(host, tmp_path, steps=2)
    during = []
    original_step = task.training_step
    task.training_step = lambda *args: (during.append(signal.getsignal(signal.SIGTERM)), original_step(*args))[1]
    before = signal.signal(signal.SIGTERM, previous_handler)
    try:
        trainer.fit()
        assert signal.getsignal(signal.SIGTERM) is previous_handler
    finally:
        signal.signal(signal.SIGTERM, before)
    assert during and all(handler is not previous_handler for handler in during)


def test_resume_refuses_a_run_whose_checkpoints_are_all_incomplete(host, tmp_path):
    trainer, _ = make_trainer(host, tmp_path, steps=4)
    trainer.fit()
    checkpoints = tmp_path / "checkpoints"
    (checkpoints / "step-00000004" / TRAINER_STATE).unlink()  # e.g. a save stopped by a second Ctrl-C
    resumed, _ = make_trainer(host, tmp_path, steps=8)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the error says it all: no warning beside it
        with pytest.raises(CheckpointError) as info:
            resumed.resume(checkpoints)
    assert str(info.value) == (
        f"{checkpoints}: holds 1 checkpoint folder(s) but no complete one (the newest, step-00000004, has no "
        f"{TRAINER_STATE}: its save was interrupted); resuming would silently restart from step 0: delete "
        f"{checkpoints} to start over"
    )
    # A run that never wrote a checkpoint still starts from step 0.
    (checkpoints / "step-00000004" / "model.safetensors").unlink()
    (checkpoints / "step-00000004").rmdir()
    assert resumed.resume(checkpoints) is False and resumed.state.step == 0


# -- falling back past a damaged newest checkpoint ------------------------------------------------


def trained(host, tmp_path):
    trainer, _ = make_trainer(host, tmp_path, steps=12)
    trainer.fit()
    return tmp_path / "checkpoints"


def resume_with_warning(host, tmp_path, checkpoints, why):
    resumed, _ = make_trainer(host, tmp_path, steps=12)
    with pytest.warns(SkippedCheckpointWarning) as caught:
        assert resumed.resume(checkpoints)
    assert [str(w.message) for w in caught] == [f"checkpoint {checkpoints / 'step-00000012'} skipped: {why}"]
    assert resumed.state.step == 8
    return resumed


def test_resume_falls_back_past_a_truncated_module_file(host, tmp_path):
    checkpoints = trained(host, tmp_path)
    module_file = checkpoints / "step-00000012" / "model.safetensors"
    module_file.write_bytes(module_file.read_bytes()[:-7])
    resume_with_warning(
        host,
        tmp_path,
        checkpoints,
        "model.safetensors is not a readable safetensors file "
        "(Error while deserializing header: incomplete metadata, file "
        "not fully covered)",
    )


def test_resume_falls_back_past_a_missing_module_file(host, tmp_path):
    checkpoints = trained(host, tmp_path)
    (checkpoints / "step-00000012" / "model.safetensors").unlink()
    resume_with_warning(host, tmp_path, checkpoints, "model.safetensors is missing")


def test_resume_falls_back_past_an_unreadable_trainer_state(host, tmp_path):
    checkpoints = trained(host, tmp_path)
    (checkpoints / "step-00000012" / TRAINER_STATE).write_bytes(b"\x00" * 5)
    resume_with_warning(
        host,
        tmp_path,
        checkpoints,
        f"{TRAINER_STATE} is unreadable (Error while deserializing header: header too small)",
    )


def test_resume_falls_back_past_an_interrupted_save(host, tmp_path):
    checkpoints = trained(host, tmp_path)
    (checkpoints / "step-00000012" / TRAINER_STATE).unlink()
    resume_with_warning(host, tmp_path, checkpoints, f"no {TRAINER_STATE}: its save was interrupted")


def test_readers_name_the_files_they_need(host, tmp_path):
    checkpoints = trained(host, tmp_path)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # none is good: the caller's error says so, no warnings
        assert latest_good_checkpoint(checkpoints, required_files=("decoder.safetensors",)) is None
    assert no_good_checkpoint(checkpoints, ("decoder.safetensors",)) == (
        f"{checkpoints}: holds 3 checkpoint folder(s) but no complete one (the newest, step-00000012, is unusable: "
        "decoder.safetensors is missing)"
    )
    (checkpoints / "step-00000004" / "decoder.safetensors").write_bytes(
        (checkpoints / "step-00000004" / "model.safetensors").read_bytes()
    )
    with pytest.warns(SkippedCheckpointWarning) as caught:
        assert latest_good_checkpoint(checkpoints, required_files=("decoder.safetensors",)).name == "step-00000004"
    assert [str(w.message) for w in caught] == [
        f"checkpoint {checkpoints / f'step-{step:08d}'} skipped: decoder.safetensors is missing" for step in (12, 8)
    ]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert latest_good_checkpoint(checkpoints, required_files=("model.safetensors",)).name == "step-00000012"
        assert latest_good_checkpoint(tmp_path / "nothing") is None


def test_folders_are_ordered_by_step_number(host, tmp_path):
    checkpoints = trained(host, tmp_path)
    # As text, "step-99999999" sorts after "step-100000000".
    (checkpoints / "step-00000008").rename(checkpoints / "step-99999999")
    (checkpoints / "step-00000012").rename(checkpoints / "step-100000000")
    assert latest_good_checkpoint(checkpoints).name == "step-100000000"
    assert latest_checkpoint(checkpoints).name == "step-100000000"


def test_resume_from_a_named_step_folder(host, tmp_path):
    checkpoints = trained(host, tmp_path)
    resumed, _ = make_trainer(host, tmp_path, steps=12)
    assert resumed.resume(checkpoints / "step-00000008") and resumed.state.step == 8
    (checkpoints / "step-00000004" / "model.safetensors").unlink()
    with pytest.raises(CheckpointError, match=r"step-00000004: cannot resume from it: model.safetensors is missing"):
        resumed.resume(checkpoints / "step-00000004")


# -- a full disk ------------------------------------------------------------------------------------


def test_disk_full_while_saving_keeps_the_previous_checkpoint(host, tmp_path, monkeypatch):
    import vqtouch.plugins.training.trainer_state as training

    trainer, _ = make_trainer(host, tmp_path, steps=8)

    def no_space(tensors, path, metadata=None):
        raise OSError(errno.ENOSPC, "No space left on device")

    with monkeypatch.context() as patch:
        real = training.save_file
        patch.setattr(
            training,
            "save_file",
            lambda tensors, path, metadata=None: (
                no_space(tensors, path) if trainer.state.step == 8 else real(tensors, path, metadata=metadata)
            ),
        )
        with pytest.raises(CheckpointError) as info:
            trainer.fit()
    checkpoints = tmp_path / "checkpoints"
    assert str(info.value) == (
        f"{checkpoints / 'step-00000008' / TRAINER_STATE}: could not write the checkpoint "
        "file: No space left on device; free disk space and run again (nothing was "
        "replaced; the run's last complete checkpoint is step-00000004)"
    )
    # The half-written step is removed, the previous one is intact and resumable.
    assert sorted(p.name for p in checkpoints.iterdir()) == ["step-00000004"]
    assert not list(checkpoints.rglob("*.tmp"))
    resumed, _ = make_trainer(host, tmp_path, steps=8)
    assert resumed.resume(checkpoints) and resumed.state.step == 4


# -- leftovers ----------------------------------------------------------------------------------


def test_resume_drops_the_metric_lines_after_the_resumed_step(host, tmp_path):
    run = RunDir(tmp_path)
    run.log_metrics("data", 7, {"images": 3.0})  # another stage's line: kept whatever its step
    trainer, _ = make_trainer(host, tmp_path, steps=6, run=run, stage="tokenizer")
    trainer.fit()  # checkpoints at 4 and 6, metric lines for steps 1..6
    (tmp_path / "checkpoints" / "step-00000006" / TRAINER_STATE).unlink()  # resume goes back to step 4
    with open(tmp_path / "metrics.jsonl", "a", encoding="utf-8") as handle:
        handle.write('{"stage": "tokenizer", "st')  # an append cut short by a kill
    resumed, _ = make_trainer(host, tmp_path, steps=6, run=run, stage="tokenizer")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SkippedCheckpointWarning)  # step-00000006 is skipped: tested above
        assert resumed.resume(tmp_path / "checkpoints")
    resumed.fit()
    records = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert [(r["stage"], r["step"]) for r in records] == [("data", 7)] + [("tokenizer", s) for s in range(1, 7)]


def test_rewind_metrics_rewrites_only_when_needed(tmp_path):
    path = tmp_path / "metrics.jsonl"
    assert rewind_metrics(path, "train", 3) == 0 and not path.exists()
    path.write_text('{"stage": "train", "step": 2}\n{"stage": "train", "step": 5}\n{"stage": "eval", "step": 9}\n')
    assert rewind_metrics(path, "train", 3) == 1
    assert path.read_text() == '{"stage": "train", "step": 2}\n{"stage": "eval", "step": 9}\n'
    before = path.stat().st_mtime_ns
    assert rewind_metrics(path, "train", 3) == 0 and path.stat().st_mtime_ns == before


def test_a_new_trainer_removes_leftovers_of_interrupted_writes(host, tmp_path):
    trained(host, tmp_path)
    checkpoints = tmp_path / "checkpoints"
    leftovers = [
        checkpoints / "step-00000012" / ".model.safetensors.k2x9_a1b.tmp",  # atomic_write's temporary
        checkpoints / "step-00000012" / ".tmpAb3xYz",  # the one safetensors writes inside it
        checkpoints / ".notes.txt.abcd1234.tmp",
    ]
    kept = [
        checkpoints / "step-00000012" / "notes.tmp",
        checkpoints / "step-00000012" / ".model.safetensors.tmp",
        tmp_path / ".model.safetensors.k2x9_a1b.tmp",
        checkpoints / ".tmpAb3xYz",
    ]
    for path in leftovers + kept:
        path.write_bytes(b"x" * 1000)
    make_trainer(host, tmp_path)
    assert [path.exists() for path in leftovers] == [False] * len(leftovers)
    assert [path.exists() for path in kept] == [True] * len(kept)


def test_only_the_newest_checkpoints_are_kept(host, tmp_path):
    trainer, _ = make_trainer(host, tmp_path, steps=20, keep_last=2)
    trainer.fit()
    checkpoints = tmp_path / "checkpoints"
    assert sorted(p.name for p in checkpoints.iterdir()) == ["step-00000016", "step-00000020"]
    # Resumed at an older step, a folder newer than the one just written is left alone.
    (checkpoints / "step-00000020" / "model.safetensors").unlink()
    resumed, _ = make_trainer(host, tmp_path, steps=18, keep_last=1)
    with pytest.warns(SkippedCheckpointWarning):
        assert resumed.resume(checkpoints) and resumed.state.step == 16
    resumed.fit()
    assert sorted(p.name for p in checkpoints.iterdir()) == ["step-00000018", "step-00000020"]


def test_keep_last_is_documented_and_bounded():
    assert TrainConfig().keep_last == 3 and TrainConfig.model_fields["keep_last"].description
    with pytest.raises(ValueError):
        TrainConfig(keep_last=0)


# -- the best checkpoint by validation score ------------------------------------------------------


class ScoredTask(toy.ToyTask):
    """The toy task with a scripted held-out score per checkpoint step, drawing random numbers while it
    scores (which must not change the training)."""

    def __init__(self, host, scores):
        super().__init__(host)
        self.scores = scores

    def validation_loss(self, batch, trainer):
        torch.rand(100)  # scoring consumes the global RNG; the trainer must put it back
        self.modules["model"].eval()  # and may switch modes; the trainer puts them back too
        return torch.full((len(batch["tactile"]),), self.scores[trainer.state.step])


def scored_trainer(host, tmp_path, scores, steps=20, run=None, **config):
    torch.manual_seed(0)
    options = {"steps": steps, "learning_rate": 0.05, "checkpoint_every": 4, "log_every": 1, "keep_last": 2, **config}
    task = ScoredTask(host, scores)
    return Trainer(
        task,
        toy.ToyDataset(),
        TrainConfig(**options),
        batch_size=4,
        seed=3,
        device=torch.device("cpu"),
        checkpoint_dir=tmp_path / "checkpoints",
        host=host,
        run=run,
        val_dataset=toy.ToyDataset(6),
    ), task


SCORES = {4: 0.5, 8: 0.2, 12: 0.9, 16: 0.7, 20: 0.8, 24: 0.1, 28: 0.6}


def test_the_best_checkpoint_is_kept_beside_the_newest(host, tmp_path):
    from vqtouch.core import resolve_config

    # A run whose config names the toy module, so that the run's checkpoint check accepts its files.
    config = resolve_config(
        "label-to-touch", overrides=['generator.conditioners=[{"name": "toy_regressor"}]'], host=host
    )
    run = RunDir.create(config, host=host, path=tmp_path / "run")
    trainer, task = scored_trainer(host, tmp_path / "run", SCORES, run=run)
    state = trainer.fit()
    checkpoints = tmp_path / "run" / "checkpoints"
    assert sorted(p.name for p in checkpoints.iterdir()) == ["step-00000008", "step-00000016", "step-00000020"]
    assert (state.best_step, state.best_score) == (8, pytest.approx(0.2))
    logged = [json.loads(line) for line in (run.path / "metrics.jsonl").read_text().splitlines()]
    assert [(line["step"], round(line["val_loss"], 6)) for line in logged if "val_loss" in line] == [
        (step, SCORES[step]) for step in (4, 8, 12, 16, 20)
    ]
    assert run.checkpoint(host, step="best") == checkpoints / "step-00000008"
    # Scoring changed nothing in the training: the same losses as without it.
    plain, plain_task = scored_trainer(host, tmp_path / "plain", SCORES, keep_best=False)
    plain.fit()
    assert plain_task.losses == task.losses
    assert sorted(p.name for p in (tmp_path / "plain" / "checkpoints").iterdir()) == ["step-00000016", "step-00000020"]


def test_a_resumed_run_remembers_its_best_checkpoint(host, tmp_path):
    trainer, _ = scored_trainer(host, tmp_path, SCORES)
    trainer.fit()
    resumed, _ = scored_trainer(host, tmp_path, SCORES, steps=28, keep_last=1)
    assert resumed.resume(tmp_path / "checkpoints") and resumed.state.best_step == 8
    resumed.fit()  # step 24 scores 0.1: the new best replaces step 8
    assert sorted(p.name for p in (tmp_path / "checkpoints").iterdir()) == ["step-00000024", "step-00000028"]
    assert resumed.state.best_step == 24


def test_non_finite_scores_are_never_best(host, tmp_path):
    trainer, _ = scored_trainer(host, tmp_path, {**SCORES, 4: float("nan"), 8: float("inf")}, steps=12)
    assert trainer.fit().best_step == 12

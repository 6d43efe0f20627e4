"""Launched by test_training under torchrun: trains the toy task on 2 gloo processes and saves
each rank's final parameters (with ``signal``: rank 1 alone is sent SIGTERM during step 3, and
each rank writes where it stopped)."""

import os
import signal
import sys
from pathlib import Path

import torch

from vqtouch.core import load_plugins
from vqtouch.plugins.training.settings import TrainConfig
from vqtouch.plugins.training.trainer import Trainer, TrainingInterrupted


def main() -> None:
    import importlib.util
    import types

    spec = importlib.util.spec_from_file_location(
        "toy_training", Path(__file__).resolve().parents[1] / "test_training.py"
    )
    toy = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(toy)
    plugin = types.ModuleType("toy")
    plugin.vqtouch_register_conditioners = toy.vqtouch_register_conditioners
    host = load_plugins(autoload=False, extra=[plugin])
    out = Path(sys.argv[1])
    rank = int(os.environ["RANK"])
    torch.manual_seed(100 + rank)  # different initial weights per rank: the trainer must broadcast rank 0's
    # "signal": rank 1 alone gets SIGTERM during step 3, as when a scheduler signals one process.
    signal_rank1 = len(sys.argv) > 2 and sys.argv[2] == "signal"
    task = toy.ToyTask(host)
    if signal_rank1 and rank == 1:
        step_once = task.training_step

        def training_step(batch, step, trainer):
            if step == 3:
                os.kill(os.getpid(), signal.SIGTERM)
            return step_once(batch, step, trainer)

        task.training_step = training_step
    if rank == 0:
        torch.save(torch.cat([p.detach().flatten() for p in task.modules["model"].parameters()]), out / "initial.pt")
    trainer = Trainer(
        task,
        toy.ToyDataset(),
        TrainConfig(steps=10, learning_rate=0.05, log_every=5, checkpoint_every=100),
        batch_size=2,
        seed=1,
        device=torch.device("cpu"),
        checkpoint_dir=out / "checkpoints",
        host=host,
    )
    try:
        trainer.fit()
    except TrainingInterrupted as exc:
        (out / f"rank{rank}.stopped").write_text(f"{exc.step} {exc.cause} {exc.checkpoint}")
    params = torch.cat([p.detach().flatten() for p in task.modules["model"].parameters()])
    torch.save(params, out / f"rank{rank}.pt")
    # Tear the gloo group down before the interpreter does: left to exit, its threads can abort the
    # process ("terminate called without an active exception", seen once in a full test run).  The
    # barrier first: a rank that tore its group down while the other still talked to it aborted that
    # other rank the same way (seen again in a later full run).
    if torch.distributed.is_initialized():
        torch.distributed.barrier()
        torch.distributed.destroy_process_group()


if __name__ == "__main__":
    main()

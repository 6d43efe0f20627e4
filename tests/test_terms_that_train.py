"""Configs train what they name: the adversarial term starts inside the run (``disc_start`` a step or a
fraction of it, half way by default), and a term or schedule that would start after the last step is
said in one line before training."""

from __future__ import annotations

import json
import warnings

import generator_runs
import pytest
import torch

from vqtouch.core import load_plugins, resolve_config
from vqtouch.plugins.training.settings import TrainConfig
from vqtouch.plugins.cli.app import main
from vqtouch.plugins.training.trainer import NeverTrainsWarning, Trainer
from vqtouch.plugins.tokenizer.training import adversarial_never_trains, disc_start_step

HOST = load_plugins()

#: The tests' tiny tokenizer run with a PatchGAN, for 6 steps, logging every step.
TINY = [
    *(override for override in generator_runs.TINY_TOKENIZER if not override.startswith("tokenizer.discriminator")),
    'tokenizer.discriminator={"name": "patchgan"}',
    "tokenizer.train.steps=6",
    "tokenizer.train.log_every=1",
    "tokenizer.train.checkpoint_every=6",
    'metrics=[{"name": "psnr"}]',
]


def train_tokenizer(out, *extra):
    args = ["--no-progress", "train", "tokenizer", "--scene", "reconstruction", "--out", str(out)]
    return main([*args, *[item for override in [*TINY, *extra] for item in ("--set", override)]])


@pytest.mark.parametrize("scene", sorted(HOST.scenes))
def test_every_scene_trains_what_it_names_and_a_patchgan_added_to_it_starts_half_way(scene):
    assert adversarial_never_trains(resolve_config(scene, host=HOST).tokenizer) is None
    section = resolve_config(scene, overrides=['tokenizer.discriminator={"name": "patchgan"}'], host=HOST).tokenizer
    assert section.loss.adversarial_weight > 0 and adversarial_never_trains(section) is None
    assert disc_start_step(section.loss.disc_start, section.train.steps) == section.train.steps // 2


def test_by_default_the_discriminator_starts_half_way(tmp_path):
    assert train_tokenizer(tmp_path / "run") == 0
    lines = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    trained = {line["step"]: line for line in lines if "loss" in line and "val_loss" not in line}
    assert sorted(step for step, line in trained.items() if "d_loss" in line) == [4, 5, 6]  # steps 3..5, 1-based


def test_an_adversarial_term_that_starts_after_the_run_is_said_in_one_line(tmp_path, capsys):
    assert train_tokenizer(tmp_path / "run", "tokenizer.loss.disc_start=10") == 0
    warned = [line for line in capsys.readouterr().err.splitlines() if "never trains" in line]
    assert warned == [
        "vqtouch: warning: tokenizer.loss.disc_start=10 starts the adversarial term at step 10, after the run's "
        "last (tokenizer.train.steps=6): it never trains; lower disc_start (0.5 starts it half way), or turn it "
        "off with tokenizer.loss.adversarial_weight=0"
    ]


@pytest.mark.parametrize(
    "value, message",
    [
        ("1.0", "1.0 is a fraction of the run only below 1"),
        ("-3", "at least 0; got -3"),
        ("true", "valid integer"),
    ],
)
def test_a_disc_start_that_is_neither_a_step_nor_a_fraction_is_refused(value, message, capsys):
    assert main(["config", "show", "reconstruction", "--set", f"tokenizer.loss.disc_start={value}"]) == 2
    error = capsys.readouterr().err.strip()
    assert error.count("\n") == 0 and "tokenizer.loss.disc_start" in error and message in error


class _Task:
    def __init__(self) -> None:
        self.model = torch.nn.Linear(2, 1)
        self.modules = {"model": self.model}

    def parameter_groups(self):
        return {"model": list(self.model.parameters())}


def test_a_warm_up_longer_than_the_run_is_said():
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        Trainer(_Task(), [], TrainConfig(steps=5, warmup_steps=8), batch_size=1, seed=0,
                device=torch.device("cpu"), checkpoint_dir=None)  # fmt: skip
        Trainer(_Task(), [], TrainConfig(steps=8, warmup_steps=8), batch_size=1, seed=0,
                device=torch.device("cpu"), checkpoint_dir=None)  # fmt: skip
    said = [str(w.message) for w in caught if issubclass(w.category, NeverTrainsWarning)]
    assert said == [
        "train.warmup_steps=8 is longer than the run (train.steps=5): the learning rate never reaches its peak; "
        "lower warmup_steps or raise steps"
    ]

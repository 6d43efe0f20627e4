"""generator.train.conditioner_weights: each conditioner's share of the training steps."""

from __future__ import annotations

import pytest
from torch import nn

from vqtouch.core import ConfigError, resolve_config
from vqtouch.plugins.generator.training import GeneratorTask


def _task(weights, seed=3, count=4):
    return GeneratorTask(nn.Linear(1, 1), [nn.Linear(1, 1) for _ in range(count)], 0.1, seed, weights)


def test_the_steps_follow_the_weights():
    task = _task([4, 2, 1, 1])
    picks = [task.pick(step) for step in range(8000)]
    shares = [picks.count(index) / len(picks) for index in range(4)]
    # Binomial standard error at 8000 draws is below 0.006: 0.02 is over 3 of them.
    assert shares == pytest.approx([0.5, 0.25, 0.125, 0.125], abs=0.02)


def test_the_pick_is_a_pure_function_of_seed_and_step():
    # A resumed run must pick the same conditioner at the same step.
    assert [_task([1, 3, 1, 1]).pick(s) for s in range(200)] == [_task([1, 3, 1, 1]).pick(s) for s in range(200)]
    assert [_task([1, 3, 1, 1]).pick(s) for s in range(200)] != [
        _task([1, 3, 1, 1], seed=4).pick(s) for s in range(200)
    ]


def test_no_weights_keeps_the_equal_shares_runs_were_trained_with():
    # Runs trained before the option existed resume with the same picks.
    import torch

    expected = [
        int(torch.randint(4, (1,), generator=torch.Generator().manual_seed(3 * 1_000_003 + s))) for s in range(100)
    ]
    assert [_task(None).pick(s) for s in range(100)] == expected


@pytest.mark.parametrize(
    "weights, message",
    [
        ("[2, 1]", "has 2 weights for 4 conditioners"),
        ("[0, 1, 1, 1]", "positive finite"),
        ('["inf", 1, 1, 1]', "positive finite"),
    ],
)
def test_bad_weights_are_refused_when_the_config_loads(host, weights, message):
    with pytest.raises(ConfigError, match=message):
        resolve_config("tour", overrides=[f"generator.train.conditioner_weights={weights}"], host=host)
    with pytest.raises(ValueError, match="one weight per conditioner"):
        _task([1, 1], count=3)

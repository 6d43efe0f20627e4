"""The code judge of best of K (:mod:`vqtouch.plugins.generator.judge`): a classifier of code grids.

Its fit is checked on grids whose class is a small pattern placed anywhere (what a judge of tactile
codes must read: the contact's shape, wherever it lies), against a fit on shuffled labels, and for
determinism and for leaving the global random state alone."""

import pytest
import torch

from vqtouch.plugins.generator.judge import CodeJudge, fit_code_judge

CODES = 12


def _pattern_grids(count: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(count, 6, 6) grids of background code 0 with one 2x2 patch, at a random place, whose codes say
    the class: class c paints codes (c + 1, c + 5) in a checkerboard; 3 classes."""
    draws = torch.Generator().manual_seed(seed)
    labels = torch.randint(3, (count,), generator=draws)
    grids = torch.zeros(count, 6, 6, dtype=torch.long)
    for index, label in enumerate(labels.tolist()):
        row, col = torch.randint(5, (2,), generator=draws).tolist()
        patch = torch.tensor([[label + 1, label + 5], [label + 5, label + 1]])
        grids[index, row : row + 2, col : col + 2] = patch
    return grids, labels


def _codebook() -> torch.Tensor:
    return torch.randn(CODES, 4, generator=torch.Generator().manual_seed(3))


def _accuracy(judge: CodeJudge, grids: torch.Tensor, labels: torch.Tensor) -> float:
    with torch.no_grad():
        return float((judge(grids).argmax(1) == labels).float().mean())


def test_the_judge_names_a_pattern_wherever_it_lies_and_not_from_shuffled_labels():
    grids, labels = _pattern_grids(64, seed=0)
    held_grids, held_labels = _pattern_grids(64, seed=1)
    judge = fit_code_judge(grids, labels, _codebook(), 3, epochs=20, seed=0)
    assert _accuracy(judge, held_grids, held_labels) >= 0.9
    shuffled = labels[torch.randperm(len(labels), generator=torch.Generator().manual_seed(5))]
    blind = fit_code_judge(grids, shuffled, _codebook(), 3, epochs=20, seed=0)
    assert _accuracy(blind, held_grids, held_labels) <= 0.6
    # rank is the log-probability of each row's own label.
    log_p = judge.rank(held_grids[:5], held_labels[:5])
    assert log_p.shape == (5,) and bool((log_p <= 0).all())
    assert torch.allclose(log_p.exp(), judge(held_grids[:5]).softmax(1)[torch.arange(5), held_labels[:5]], atol=1e-6)


def test_the_fit_is_deterministic_and_leaves_the_global_random_state_alone():
    grids, labels = _pattern_grids(32, seed=2)
    torch.manual_seed(123)
    before = torch.rand(3)
    torch.manual_seed(123)
    first = fit_code_judge(grids, labels, _codebook(), 3, epochs=3, seed=7)
    after = torch.rand(3)
    second = fit_code_judge(grids, labels, _codebook(), 3, epochs=3, seed=7)
    assert torch.equal(before, after)
    for a, b in zip(first.state_dict().values(), second.state_dict().values(), strict=True):
        assert torch.equal(a, b)
    third = fit_code_judge(grids, labels, _codebook(), 3, epochs=3, seed=8)
    assert not torch.equal(first.net[0].weight, third.net[0].weight)


@pytest.mark.parametrize(
    ("codes", "labels", "message"),
    [
        (torch.zeros(4, 6), torch.zeros(4), "expected codes"),
        (torch.zeros(4, 6, 6), torch.zeros(3), "expected codes"),
        (torch.zeros(4, 6, 6), torch.full((4,), 3), r"labels must lie in \[0, 3\)"),
    ],
)
def test_bad_inputs_are_refused_with_what_was_wrong(codes, labels, message):
    with pytest.raises(ValueError, match=message):
        fit_code_judge(codes.long(), labels.long(), _codebook(), 3, epochs=1)

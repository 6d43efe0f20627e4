"""Best of K for label conditions: candidates drawn per condition, the one the generator's
own class posterior (or the run's code judge) ranks highest kept.

A tiny label-to-touch run supplies a real generator and label conditioner; the likelihood estimate is
checked against a reading through the generator's public ``log_x0``, the selection against an
exhaustive argmax over every candidate, and one candidate against plain sampling, bit for bit."""

import json

import pytest
import torch

from vqtouch.core import ConfigError, load_plugins
from vqtouch.plugins.cli.app import main
from vqtouch.plugins.generator import load_pipeline
from vqtouch.plugins.generator.best_of import MAX_BEST_OF, candidate_seed, check_best_of, sample_best_of
from vqtouch.plugins.generator.judge import codebook_of
from vqtouch.plugins.generator.posterior import class_log_posteriors
from vqtouch.plugins.generator.vq_diffusion import likelihood_steps

from cli_checks import one_error_line

HOST = load_plugins(autoload=False)


@pytest.fixture(scope="module")
def pipe(tiny_label_run):
    return load_pipeline(tiny_label_run, host=HOST)


def test_likelihood_steps_are_distinct_interior_steps():
    assert likelihood_steps(100) == [20, 40, 60, 80]
    assert likelihood_steps(20) == [4, 8, 12, 16]
    assert likelihood_steps(2) == [1]
    for steps in range(2, 60):
        found = likelihood_steps(steps)
        assert found == sorted(set(found)) and all(1 <= t <= steps - 1 for t in found)


def test_the_likelihood_estimate_matches_a_reading_through_log_x0_and_ignores_its_batch(pipe):
    generator, conditioner = pipe.generator, pipe.conditioners[0]
    schedule, length = generator.schedule, generator.length
    codes_BHW = torch.randint(
        0, generator.num_codes, (3, *generator.grid_hw), generator=torch.Generator().manual_seed(1)
    )
    condition = conditioner(torch.tensor([0, 1, 2]))
    codes_BL = codes_BHW.flatten(1)
    reference_B = torch.zeros(3)
    for t in likelihood_steps(generator.config.num_steps):
        # The documented rule: each cell masked with probability gamma_bar_t, from a generator seeded by t.
        masked_L = torch.rand(length, generator=torch.Generator().manual_seed(t)) < float(schedule.gamma_bar[t])
        assert 0 < int(masked_L.sum()) < length
        codes_t_BL = torch.where(masked_L, schedule.mask_index, codes_BL)
        log_x0_BCL = generator.log_x0(codes_t_BL, torch.full((3,), t), condition)
        reference_B += (log_x0_BCL.gather(1, codes_BL[:, None]).squeeze(1) * masked_L).sum(1)
    estimate_B = generator.masked_log_likelihood(codes_BHW, condition)
    assert torch.isfinite(estimate_B).all() and (estimate_B < 0).all()
    torch.testing.assert_close(estimate_B, reference_B, rtol=1e-5, atol=1e-4)
    alone = generator.masked_log_likelihood(codes_BHW[1:2], conditioner(torch.tensor([1])))
    torch.testing.assert_close(alone, estimate_B[1:2], rtol=1e-5, atol=1e-4)


def test_class_posteriors_are_normalised_over_every_class(pipe):
    generator, conditioner = pipe.generator, pipe.conditioners[0]
    codes_BHW = torch.randint(
        0, generator.num_codes, (2, *generator.grid_hw), generator=torch.Generator().manual_seed(2)
    )
    log_posterior_CB = class_log_posteriors(generator, conditioner, codes_BHW)
    assert log_posterior_CB.shape == (conditioner.num_classes, 2)
    torch.testing.assert_close(log_posterior_CB.exp().sum(0), torch.ones(2))


def test_each_row_keeps_the_candidate_its_label_ranks_highest(pipe):
    generator, conditioner = pipe.generator, pipe.conditioners[0]
    labels_B = torch.tensor([0, 1, 2, 1])
    condition = conditioner(labels_B)
    sampler = HOST.build("sampler", "posterior")
    row_seeds = [11, 12, 13, 14]

    def draw(generators):
        return generator.sample(condition, sampler, steps=3, generators=generators)

    chosen = sample_best_of(generator, conditioner, labels_B, row_seeds, 4, draw, torch.device("cpu"))
    # Exhaustively: every candidate drawn with its documented seed, scored, the best kept.
    candidates_KBHW = torch.stack(
        [draw([torch.Generator().manual_seed(candidate_seed(s, k)) for s in row_seeds]) for k in range(4)]
    )
    scores_KB = torch.stack(
        [class_log_posteriors(generator, conditioner, codes)[labels_B, torch.arange(4)] for codes in candidates_KBHW]
    )
    expected = candidates_KBHW[scores_KB.argmax(0), torch.arange(4)]
    assert torch.equal(chosen, expected)
    # Candidate 0 is each row's own draw; the others differ from it (four rows, three candidates each).
    assert torch.equal(candidates_KBHW[0], draw([torch.Generator().manual_seed(s) for s in row_seeds]))
    assert not torch.equal(candidates_KBHW[1], candidates_KBHW[0])


def test_a_given_rank_replaces_the_posterior_and_its_best_candidate_is_kept(pipe):
    generator, conditioner = pipe.generator, pipe.conditioners[0]
    labels_B = torch.tensor([2, 0, 1])
    condition = conditioner(labels_B)
    sampler = HOST.build("sampler", "posterior")
    row_seeds = [21, 22, 23]

    def draw(generators):
        return generator.sample(condition, sampler, steps=3, generators=generators)

    ranker = pipe.best_of_ranking("judge")
    judge = ranker.judge
    assert pipe.best_of_ranking("judge") is ranker and ranker.judge is judge  # fitted once per loaded run
    chosen = sample_best_of(generator, conditioner, labels_B, row_seeds, 3, draw, torch.device("cpu"), rank=ranker)
    candidates_KBHW = torch.stack(
        [draw([torch.Generator().manual_seed(candidate_seed(s, k)) for s in row_seeds]) for k in range(3)]
    )
    scores_KB = torch.stack([judge.rank(codes, labels_B) for codes in candidates_KBHW])
    assert torch.equal(chosen, candidates_KBHW[scores_KB.argmax(0), torch.arange(3)])
    # The judge reads the run's own codebook, frozen.
    assert torch.allclose(
        judge.embed.weight,
        torch.nn.functional.normalize(codebook_of(pipe.tokenizer), dim=1) * judge.embed.weight.shape[1] ** 0.5,
    )
    assert not judge.embed.weight.requires_grad
    with pytest.raises(ConfigError, match="--best-of-rank 'best': choose one of consensus, judge, posterior$"):
        pipe(label=[0], steps=3, best_of=2, best_of_rank="best")


def test_one_candidate_is_plain_sampling_bit_for_bit(pipe):
    plain = pipe(label=[0, 1, 2], steps=3, seed=5)
    assert torch.equal(pipe(label=[0, 1, 2], steps=3, seed=5, best_of=1), plain)
    best = pipe(label=[0, 1, 2], steps=3, seed=5, best_of=3)
    assert best.shape == plain.shape and torch.isfinite(best).all()


def test_candidate_seeds_differ_where_a_cpu_generator_reads_them():
    # A CPU torch.Generator reads the low 32 bits of its seed: that is where candidates must differ.
    rows = range(1000)
    assert all(candidate_seed(row, 0) == row for row in rows)
    for row in rows:
        own = {candidate_seed(row, k) % 2**32 for k in range(MAX_BEST_OF)}
        assert len(own) == MAX_BEST_OF
    # Across rows, only the chance collisions of 63,000 hashes in 2**32 values (about 0.5 expected).
    low_bits = [candidate_seed(row, k) % 2**32 for row in rows for k in range(1, MAX_BEST_OF)]
    assert len(low_bits) - len(set(low_bits)) <= 3 and not set(low_bits) & set(rows)
    assert all(0 <= candidate_seed(2**62 + row, 5) < 2**63 for row in rows)
    with pytest.raises(ValueError, match="candidate 64 must lie in"):
        candidate_seed(3, MAX_BEST_OF)


class _ImageConditioner:
    """Stands for any conditioner without a finite set of classes (an image's, a text's)."""


@pytest.mark.parametrize("best_of", [0, MAX_BEST_OF + 1, True, 2.0])
def test_a_bad_count_is_refused(pipe, best_of):
    with pytest.raises(ConfigError, match=f"--best-of {best_of}: give an integer in"):
        check_best_of(best_of, pipe.conditioners[0], "0:label")


def test_a_conditioner_without_classes_is_refused_above_one_candidate():
    assert check_best_of(1, _ImageConditioner(), "1:visual") == 1
    with pytest.raises(ConfigError, match="conditioner 1:visual has no finite set of classes"):
        check_best_of(2, _ImageConditioner(), "1:visual")


def test_the_commands_draw_the_best_of_k_and_say_so(tiny_label_run, tmp_path, capsys):
    run = tiny_label_run
    out = tmp_path / "gen"
    assert main(["generate", "--run", str(run), "--label", "1", "--n", "2", "--steps", "3", "--best-of", "2",
                 "--out", str(out)]) == 0  # fmt: skip
    assert json.loads((out / "generate.json").read_text())["best_of"] == 2
    assert json.loads((out / "generate.json").read_text())["best_of_rank"] == "judge"
    scored = tmp_path / "scored"
    args = ["evaluate", "generation", "--run", str(run), "--n", "3", "--steps", "3", "--best-of", "2"]
    assert main([*args, "--out", str(scored)]) == 0
    scores = json.loads((scored / "generation.json").read_text())["by_conditioner"]["0:label"]
    assert scores["best_of"] == 2 and scores["best_of_rank"] == "judge"
    posterior = tmp_path / "posterior"
    assert main([*args, "--best-of-rank", "posterior", "--out", str(posterior)]) == 0
    scores = json.loads((posterior / "generation.json").read_text())["by_conditioner"]["0:label"]
    assert scores["best_of_rank"] == "posterior"
    capsys.readouterr()
    never = tmp_path / "never"
    assert main(["generate", "--run", str(run), "--label", "1", "--best-of", "65", "--out", str(never)]) == 2
    assert one_error_line(capsys).startswith("--best-of 65: give an integer in [1, 64]") and not never.exists()

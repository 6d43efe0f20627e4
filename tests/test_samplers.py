"""Tests of the discrete-diffusion samplers (vqtouch.plugins.generator.samplers).

The denoisers here are synthetic and row-wise, so every property is checkable: an oracle (one-hot of a
known code grid), a fixed per-position categorical independent of x_t, and a context-dependent one whose
prediction depends on the row's current codes and timestep (so randomness propagates through the chain).
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from vqtouch.core import ConfigError, Sampler, load_plugins
from vqtouch.plugins.generator import samplers as S
from vqtouch.plugins.generator.diffusion import LOG_ZERO, MaskReplaceSchedule, log_onehot, log_predict_x0

K = 6
T = 10
NAMES = ("posterior", "purity", "confidence")
#: A schedule with real replacement noise (K beta_bar up to 0.05), next to the released, effectively pure-mask one.
REPLACE_ENDS = {"att_1": 0.99, "att_T": 0.05, "ctt_1": 0.005, "ctt_T": 0.9}


def make(name: str, **options) -> Sampler:
    """The sampler registered as ``name``, built directly (the host is tested separately)."""
    return {"posterior": S.PosteriorSampler, "purity": S.PuritySampler, "confidence": S.ConfidenceSampler}[name](
        **options
    )


def gens(*seeds: int) -> list[torch.Generator]:
    """One CPU generator per row, seeded with ``seeds``."""
    return [torch.Generator().manual_seed(seed) for seed in seeds]


class Recorder:
    """Wraps a denoiser and records the codes and timesteps of every call."""

    def __init__(self, denoise):
        self.denoise = denoise
        self.codes: list[torch.Tensor] = []
        self.t: list[torch.Tensor] = []

    def __call__(self, codes_BL: torch.Tensor, t_B: torch.Tensor) -> torch.Tensor:
        self.codes.append(codes_BL.clone())
        self.t.append(t_B.clone())
        return self.denoise(codes_BL, t_B)

    @property
    def calls(self) -> int:
        return len(self.t)

    def masked_counts(self, mask_index: int, row: int = 0) -> list[int]:
        return [int((codes_BL[row] == mask_index).sum()) for codes_BL in self.codes]


def oracle(target_L: torch.Tensor, num_codes: int):
    """p(x0 | x_t) = one-hot of ``target_L`` at every step."""

    def denoise(codes_BL: torch.Tensor, t_B: torch.Tensor) -> torch.Tensor:
        return log_onehot(target_L.expand(codes_BL.shape[0], -1), num_codes + 1)

    return denoise


def fixed(probs_KL: torch.Tensor):
    """p(x0 | x_t) = ``probs_KL`` at every step, whatever x_t."""
    log_x0_CL = torch.cat([probs_KL.log(), torch.full_like(probs_KL[:1], LOG_ZERO)])

    def denoise(codes_BL: torch.Tensor, t_B: torch.Tensor) -> torch.Tensor:
        return log_x0_CL.expand(codes_BL.shape[0], -1, -1).clone()

    return denoise


def contextual(num_codes: int, length: int, seed: int = 0):
    """A row-wise denoiser that depends on x_t and t: a fixed random base, plus a bonus for the code of the
    previous position once it is revealed, plus a t-dependent bias on code 0."""
    base_KL = torch.randn(num_codes, length, generator=torch.Generator().manual_seed(seed))

    def denoise(codes_BL: torch.Tensor, t_B: torch.Tensor) -> torch.Tensor:
        previous_BL = codes_BL.roll(1, dims=1)
        bonus_BKL = torch.zeros(codes_BL.shape[0], num_codes + 1, length).scatter_(1, previous_BL.unsqueeze(1), 2.0)
        logits_BKL = base_KL + bonus_BKL[:, :num_codes]
        logits_BKL[:, 0] += 0.2 * t_B.view(-1, 1).float()
        return log_predict_x0(logits_BKL)

    return denoise


# -- correctness with an oracle ---------------------------------------------------------------------


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("steps", [1, 2, 5, T])
@pytest.mark.parametrize("length", [1, 16])
def test_oracle_denoiser_gives_the_target(name, steps, length):
    schedule = MaskReplaceSchedule(K, T)
    target_L = torch.randint(0, K, (length,), generator=torch.Generator().manual_seed(length + steps))
    codes_BL = make(name).sample(oracle(target_L, K), schedule, length=length, steps=steps, generators=gens(1, 2, 3))
    assert codes_BL.dtype == torch.long and codes_BL.shape == (3, length)
    assert torch.equal(codes_BL, target_L.expand(3, -1))


def test_posterior_without_keeping_follows_the_posterior_to_the_oracle_target_under_replace_noise():
    schedule = MaskReplaceSchedule(K, T, **REPLACE_ENDS)
    target_L = torch.arange(16) % K
    for steps in (1, 3, T):
        codes_BL = S.PosteriorSampler(keep_unmasked=False).sample(
            oracle(target_L, K), schedule, length=16, steps=steps, generators=gens(*range(8))
        )
        assert torch.equal(codes_BL, target_L.expand(8, -1))


def test_schedules_without_gamma_bar_map_the_mask_ratio_linearly():
    bare = SimpleNamespace(num_codes=K, num_steps=T, mask_index=K)
    target_L = torch.arange(8) % K
    recorder = Recorder(oracle(target_L, K))
    codes_BL = S.ConfidenceSampler().sample(recorder, bare, length=8, steps=4, generators=gens(0))
    assert torch.equal(codes_BL[0], target_L)
    fractions = [count / 8 for count in recorder.masked_counts(K)]
    assert [int(t_B[0]) for t_B in recorder.t] == [min(range(T), key=lambda t: abs((t + 1) / T - f)) for f in fractions]


# -- number of calls and timesteps ------------------------------------------------------------------


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("steps", [1, 2, 5, T])
def test_each_sampler_calls_denoise_steps_times(name, steps):
    recorder = Recorder(contextual(K, 16))
    make(name).sample(recorder, MaskReplaceSchedule(K, T), length=16, steps=steps, generators=gens(0, 1))
    assert recorder.calls == steps


def test_with_more_steps_than_tokens_mask_decoders_stop_once_everything_is_revealed():
    schedule = MaskReplaceSchedule(K, T)
    counts = {}
    for name in NAMES:
        recorder = Recorder(contextual(K, 4))
        codes_BL = make(name).sample(recorder, schedule, length=4, steps=T, generators=gens(0))
        assert (codes_BL < K).all()
        counts[name] = recorder.calls
    # The chain's length does not depend on L; purity and confidence reveal at least one token per call.
    assert counts == {"posterior": T, "purity": 4, "confidence": 4}


def test_strided_timesteps_span_the_whole_chain():
    assert S.strided_timesteps(T, 1) == [T - 1]
    assert S.strided_timesteps(T, 2) == [T - 1, 0]
    assert S.strided_timesteps(T, T) == list(range(T - 1, -1, -1))
    assert S.strided_timesteps(100, 5) == [99, 74, 50, 25, 0]
    for num_steps in (2, 3, 7, 100):
        for steps in range(1, num_steps + 1):
            points = S.strided_timesteps(num_steps, steps)
            assert len(points) == steps and points[0] == num_steps - 1
            assert points[-1] == (0 if steps > 1 else num_steps - 1)
            gaps = [a - b for a, b in zip(points, points[1:])]
            assert all(gap >= 1 for gap in gaps)
            if gaps:  # evenly spaced: gaps differ by at most one
                assert max(gaps) - min(gaps) <= 1


@pytest.mark.parametrize("steps", [1, 3, 5, T])
def test_posterior_walks_strided_timesteps_and_jumps_to_the_next_one(steps):
    schedule = MaskReplaceSchedule(K, T)
    jumps = []
    exact_posterior = schedule.posterior

    def recording_posterior(log_x0_BCL, codes_t_BL, t_B, s_B=None):
        jumps.append((int(t_B[0]), int(s_B[0])))
        return exact_posterior(log_x0_BCL, codes_t_BL, t_B, s_B)

    schedule.posterior = recording_posterior
    recorder = Recorder(contextual(K, 8))
    S.PosteriorSampler().sample(recorder, schedule, length=8, steps=steps, generators=gens(0, 1))
    seen = [int(t_B[0]) for t_B in recorder.t]
    assert all(torch.equal(t_B, torch.full_like(t_B, t_B[0])) for t_B in recorder.t)
    # Starts at T-1 (the diffusers pitfall would start at steps-1 from all MASK), strictly decreasing, to 0.
    assert seen[0] == T - 1
    assert all(a > b for a, b in zip(seen, seen[1:]))
    assert seen[-1] == (0 if steps > 1 else T - 1)
    assert seen == S.strided_timesteps(T, steps)
    # Each posterior jumps across the skip to the next point, the last one to x_0 (s = -1).
    assert jumps == list(zip(seen, seen[1:] + [-1]))


@pytest.mark.parametrize("name", ["purity", "confidence"])
def test_mask_decoders_pass_the_timestep_matching_the_masked_fraction(name):
    schedule = MaskReplaceSchedule(K, T)
    recorder = Recorder(contextual(K, 16))
    make(name).sample(recorder, schedule, length=16, steps=6, generators=gens(0))
    gamma_bar = schedule.gamma_bar.tolist()[:T]
    expected = [min(range(T), key=lambda t: abs(gamma_bar[t] - count / 16)) for count in recorder.masked_counts(K)]
    assert [int(t_B[0]) for t_B in recorder.t] == expected
    assert expected[0] == T - 1


# -- schedules of revealed tokens -------------------------------------------------------------------


def test_confidence_follows_the_cosine_schedule():
    schedule = MaskReplaceSchedule(K, T)
    recorder = Recorder(contextual(K, 16))
    S.ConfidenceSampler().sample(recorder, schedule, length=16, steps=8, generators=gens(0))
    # floor(16 cos(pi/2 (i+1)/8)) for i = 0..6, worked out by hand.
    assert recorder.masked_counts(K) == [16, 15, 14, 13, 11, 8, 6, 3]
    # At most #masked - 1 stay masked: 4 cos(pi/2 (i+1)/10) floors to 3, 3, 3, so the clamp reveals one a call.
    recorder = Recorder(contextual(K, 4))
    S.ConfidenceSampler().sample(recorder, schedule, length=4, steps=T, generators=gens(0))
    assert recorder.masked_counts(K) == [4, 3, 2, 1]


def test_purity_follows_the_linear_schedule():
    recorder = Recorder(contextual(K, 16))
    S.PuritySampler().sample(recorder, MaskReplaceSchedule(K, T), length=16, steps=5, generators=gens(0))
    assert recorder.masked_counts(K) == [16, 13, 10, 7, 4]
    assert S.linear_masked_counts(16, 5) == [13, 10, 7, 4, 0]


def test_greedy_purity_reveals_the_purest_positions_first():
    peaks = torch.tensor([0.3, 0.9, 0.5, 0.99, 0.4, 0.7, 0.35, 0.8])
    probs_KL = torch.stack([peaks, *[(1 - peaks) / 3] * 3])  # code 0 has the peak; 4 codes
    recorder = Recorder(fixed(probs_KL))
    S.PuritySampler(randomness=0.0).sample(
        recorder, MaskReplaceSchedule(4, T), length=8, steps=4, generators=gens(0, 1)
    )
    revealed = [set(torch.nonzero(codes_BL[0] != 4).flatten().tolist()) for codes_BL in recorder.codes]
    assert revealed == [set(), {3, 1}, {3, 1, 7, 5}, {3, 1, 7, 5, 2, 4}]


def test_purity_randomness_draws_positions_in_proportion_to_purity():
    peaks = torch.tensor([0.3, 0.9, 0.5, 0.99, 0.4, 0.7, 0.35, 0.8])
    probs_KL = torch.stack([peaks, *[(1 - peaks) / 3] * 3])
    rows = 2000
    recorder = Recorder(fixed(probs_KL))
    S.PuritySampler(randomness=1.0).sample(
        recorder, MaskReplaceSchedule(4, T), length=8, steps=8, generators=gens(*range(rows))
    )
    # One token per round; with Gumbel noise of scale 1 on log-purity the first is position j with
    # probability peak_j / sum(peaks) (Gumbel-max), as Improved VQ-Diffusion's multinomial draw.
    first_B = (recorder.codes[1] != 4).float().argmax(dim=1)
    counts_L = torch.bincount(first_B, minlength=8).double()
    expected_L = rows * peaks.double() / peaks.sum()
    chi_square = float(((counts_L - expected_L) ** 2 / expected_L).sum())
    assert chi_square < 24.32, (counts_L.tolist(), chi_square)  # chi-square, 7 dof, p = 0.001


def test_confidence_without_temperature_keeps_the_most_confident_draws():
    # Positions 0..3 are certain (log p = 0), 4..7 uniform over 4 codes (log p = log 1/4).
    probs_KL = torch.full((4, 8), 0.25)
    probs_KL[:, :4] = torch.tensor([1.0, 0.0, 0.0, 0.0]).view(4, 1).clamp_min(1e-12)
    recorder = Recorder(fixed(probs_KL))
    S.ConfidenceSampler(temperature=0.0).sample(
        recorder, MaskReplaceSchedule(4, T), length=8, steps=4, generators=gens(0, 1)
    )
    revealed = [set(torch.nonzero(codes_BL[0] != 4).flatten().tolist()) for codes_BL in recorder.codes]
    # 8 cos(pi/8) -> 7 and 8 cos(pi/4) -> 5 stay masked: the 1 and then 3 revealed are certain positions.
    assert len(revealed[1]) == 1 and len(revealed[2]) == 3
    assert revealed[1] < revealed[2] <= {0, 1, 2, 3}
    # With MaskGIT's temperature the noise (scale 4.5 * 3/4 at the first iteration) sometimes keeps an
    # uncertain draw first.
    recorder = Recorder(fixed(probs_KL))
    S.ConfidenceSampler(temperature=4.5).sample(
        recorder, MaskReplaceSchedule(4, T), length=8, steps=4, generators=gens(*range(200))
    )
    first_uncertain_B = (recorder.codes[1][:, 4:] != 4).any(dim=1)
    assert 0 < int(first_uncertain_B.sum()) < 200


def test_posterior_keeps_revealed_tokens_unless_asked_not_to():
    probs_KL = torch.softmax(torch.randn(K, 16, generator=torch.Generator().manual_seed(3)), dim=0)
    schedule = MaskReplaceSchedule(K, T)
    for keep in (True, False):
        recorder = Recorder(fixed(probs_KL))
        codes_BL = S.PosteriorSampler(keep_unmasked=keep).sample(
            recorder, schedule, length=16, steps=T, generators=gens(*range(4))
        )
        states = [*recorder.codes, codes_BL]
        changed = any(((before != K) & (after != before)).any() for before, after in zip(states, states[1:]))
        # With p(x0 | x_t) not one-hot the posterior itself moves revealed tokens (the released schedule's
        # replace mass is tiny but its ratio across a skip is not): keeping them is the option's job.
        assert changed is not keep


# -- distribution -----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "name,steps", [("posterior", T), ("posterior", 3), ("posterior", 1), ("purity", T), ("confidence", T)]
)
def test_samples_follow_a_fixed_target_distribution(name, steps):
    probs_K = torch.tensor([0.1, 0.2, 0.3, 0.4])
    rows = 4000
    codes_BL = make(name).sample(
        fixed(probs_K.view(4, 1)),
        MaskReplaceSchedule(4, T),
        length=1,
        steps=steps,
        generators=gens(*range(1000, 1000 + rows)),
    )
    counts_K = torch.bincount(codes_BL.flatten(), minlength=4).double()
    expected_K = rows * probs_K.double()
    chi_square = float(((counts_K - expected_K) ** 2 / expected_K).sum())
    assert chi_square < 16.27, (counts_K.tolist(), chi_square)  # chi-square, 3 dof, p = 0.001


# -- randomness: determinism and batch-size invariance ----------------------------------------------


@pytest.mark.parametrize("name", NAMES)
def test_same_seeds_same_codes_and_rows_independent_of_their_batch(name):
    schedule = MaskReplaceSchedule(K, T)
    denoise = contextual(K, 6)
    seeds = [11, 12, 13, 14, 15]
    sampler = make(name)
    batch_BL = sampler.sample(denoise, schedule, length=6, steps=4, generators=gens(*seeds))
    assert torch.equal(batch_BL, sampler.sample(denoise, schedule, length=6, steps=4, generators=gens(*seeds)))
    for row, seed in enumerate(seeds):
        alone_1L = sampler.sample(denoise, schedule, length=6, steps=4, generators=gens(seed))
        assert torch.equal(alone_1L[0], batch_BL[row])
    # The seeds matter: 5 rows of 6 tokens over 6 codes are not all alike.
    assert len({tuple(row.tolist()) for row in batch_BL}) > 1


# -- outputs and arguments --------------------------------------------------------------------------


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("num_codes,length", [(2, 9), (16384, 3)])
def test_outputs_are_codes_never_mask(name, num_codes, length):
    schedule = MaskReplaceSchedule(num_codes, T)
    logits_KL = torch.randn(num_codes, length, generator=torch.Generator().manual_seed(0)) * 3

    def denoise(codes_BL, t_B):
        return log_predict_x0(logits_KL.expand(codes_BL.shape[0], -1, -1))

    for steps in (1, 3, T):
        codes_BL = make(name).sample(denoise, schedule, length=length, steps=steps, generators=gens(0, 1))
        assert codes_BL.dtype == torch.long and codes_BL.shape == (2, length)
        assert codes_BL.min() >= 0 and codes_BL.max() < num_codes


@pytest.mark.parametrize("name", NAMES)
def test_mass_on_mask_from_a_denoiser_never_becomes_a_mask_output(name):
    # Off contract (the MASK row should be LOG_ZERO): most of the mass on MASK must still give codes.
    log_x0_CL = torch.cat([torch.full((K, 5), math.log(0.01 / K)), torch.full((1, 5), math.log(0.99))])

    def denoise(codes_BL, t_B):
        return log_x0_CL.expand(codes_BL.shape[0], -1, -1).clone()

    codes_BL = make(name).sample(denoise, MaskReplaceSchedule(K, T), length=5, steps=3, generators=gens(*range(20)))
    assert codes_BL.max() < K


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("steps", [0, T + 1, -1, 2.0, True])
def test_steps_out_of_range_are_refused_naming_the_range(name, steps):
    with pytest.raises(ValueError, match=rf"steps must be an integer in \[1, {T}\]"):
        make(name).sample(
            oracle(torch.zeros(4, dtype=torch.long), K),
            MaskReplaceSchedule(K, T),
            length=4,
            steps=steps,
            generators=gens(0),
        )


def test_bad_lengths_generators_and_denoiser_outputs_are_refused():
    schedule = MaskReplaceSchedule(K, T)
    denoise = oracle(torch.zeros(4, dtype=torch.long), K)
    with pytest.raises(ValueError, match="length"):
        S.PosteriorSampler().sample(denoise, schedule, length=0, steps=2, generators=gens(0))
    with pytest.raises(ValueError, match="generators"):
        S.PosteriorSampler().sample(denoise, schedule, length=4, steps=2, generators=[])
    with pytest.raises(ValueError, match=r"expected \(B, K\+1, L\)"):
        S.ConfidenceSampler().sample(
            lambda codes_BL, t_B: denoise(codes_BL, t_B)[:, :K], schedule, length=4, steps=2, generators=gens(0)
        )


def test_cosine_target_matches_maskgit():
    assert [S.cosine_masked_target(16, 8, i) for i in range(8)] == [
        math.floor(16 * math.cos(math.pi / 2 * (i + 1) / 8)) for i in range(7)
    ] + [0]


# -- registration -----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def sampler_host():
    # Not yet an entry point in pyproject.toml: load the module explicitly.
    return load_plugins(autoload=False, extra=["vqtouch.plugins.generator.samplers_plugin"])


def test_every_sampler_is_registered_and_builds(sampler_host):
    assert set(NAMES) <= set(sampler_host.registry("sampler").names())
    classes = {"posterior": S.PosteriorSampler, "purity": S.PuritySampler, "confidence": S.ConfidenceSampler}
    for name in NAMES:
        sampler = sampler_host.build("sampler", {"name": name})
        assert isinstance(sampler, Sampler) and type(sampler) is classes[name]
    assert sampler_host.build("sampler", {"name": "posterior", "keep_unmasked": False}).keep_unmasked is False
    assert sampler_host.build("sampler", {"name": "purity", "randomness": 0.5}).randomness == 0.5
    assert sampler_host.build("sampler", {"name": "confidence"}).temperature == 4.5


@pytest.mark.parametrize(
    "options,message",
    [
        ({"name": "posterior", "bogus": 1}, "bogus"),
        ({"name": "confidence", "temprature": 2.0}, "temprature"),
        ({"name": "confidence", "temperature": -1.0}, "temperature"),
        ({"name": "purity", "randomness": float("nan")}, "randomness"),
    ],
)
def test_bad_sampler_options_are_refused_naming_the_option(sampler_host, options, message):
    with pytest.raises(ConfigError, match=message):
        sampler_host.build("sampler", options)

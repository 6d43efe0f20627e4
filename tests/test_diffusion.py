"""Tests of the discrete-diffusion maths (vqtouch.plugins.generator.diffusion) and of the denoiser network
(vqtouch.plugins.generator.denoiser).

References are built independently: transition matrices are dense float64 (K+1) x (K+1) matrices made
from per-step alpha_t, beta_t, gamma_t recomputed here from the end points, and posteriors follow Bayes'
rule on those matrices, never the module's O(K) log-space shortcuts.
"""

from __future__ import annotations

import decimal
import math

import pytest
import torch

from vqtouch.plugins.generator import diffusion as D
from vqtouch.plugins.generator.denoiser import DiffusionTransformer

K = 8
T = 12
L = 16
#: A schedule with real replacement noise (K beta_bar up to 0.05) next to the released, effectively pure-mask one.
REPLACE_ENDS = {"att_1": 0.99, "att_T": 0.05, "ctt_1": 0.005, "ctt_T": 0.9}
DEFAULT_ENDS = {"att_1": 0.99999, "att_T": 0.000009, "ctt_1": 0.000009, "ctt_T": 0.99999}
SCHEDULES = {"default": DEFAULT_ENDS, "replace": REPLACE_ENDS}


def gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


# -- independent float64 references ---------------------------------------------------------------


def per_step_float64(
    num_codes: int, num_steps: int, att_1: float, att_T: float, ctt_1: float, ctt_T: float
) -> list[tuple[float, float, float]]:
    """(alpha_t, beta_t, gamma_t) for t = 0..T-1 from the linear cumulative end points (docs/diffusion.md section 1)."""
    alpha_bar = [att_1 + t / (num_steps - 1) * (att_T - att_1) for t in range(num_steps)]
    gamma_bar = [ctt_1 + t / (num_steps - 1) * (ctt_T - ctt_1) for t in range(num_steps)]
    steps = []
    for t in range(num_steps):
        previous_alpha = alpha_bar[t - 1] if t else 1.0
        previous_gamma = gamma_bar[t - 1] if t else 0.0
        alpha = alpha_bar[t] / previous_alpha
        gamma = 1.0 - (1.0 - gamma_bar[t]) / (1.0 - previous_gamma)
        steps.append((alpha, (1.0 - alpha - gamma) / num_codes, gamma))
    return steps


def step_matrix(num_codes: int, alpha: float, beta: float, gamma: float) -> torch.Tensor:
    """Q[k, j] = q(next = j | previous = k), float64, MASK = num_codes absorbing."""
    matrix = torch.zeros(num_codes + 1, num_codes + 1, dtype=torch.float64)
    matrix[:num_codes, :num_codes] = beta
    matrix[:num_codes, :num_codes] += alpha * torch.eye(num_codes, dtype=torch.float64)
    matrix[:num_codes, num_codes] = gamma
    matrix[num_codes, num_codes] = 1.0
    return matrix


class DenseProcess:
    """The forward process as dense float64 matrices: ``between(s, t)`` = Q_{s+1} ... Q_t (s = -1: from x_0)."""

    def __init__(self, num_codes: int, num_steps: int, ends: dict[str, float]) -> None:
        self.num_codes = num_codes
        self.steps = [step_matrix(num_codes, *abg) for abg in per_step_float64(num_codes, num_steps, **ends)]

    def between(self, s: int, t: int) -> torch.Tensor:
        matrix = torch.eye(self.num_codes + 1, dtype=torch.float64)
        for step in range(s + 1, t + 1):
            matrix = matrix @ self.steps[step]
        return matrix

    def bayes(self, x0: int, xt: int, t: int, s: int) -> torch.Tensor:
        """q(x_s | x_t, x_0) over all K+1 states, by Bayes' rule on the matrices."""
        joint = self.between(-1, s)[x0, :] * self.between(s, t)[:, xt]
        return joint / self.between(-1, t)[x0, xt]


def assert_log_close(
    log_actual: torch.Tensor,
    reference: torch.Tensor,
    prob_atol: float = 1e-6,
    log_atol: float = 1e-4,
    significant: float = 1e-9,
) -> None:
    """Probabilities agree to ``prob_atol`` everywhere, and logs agree to ``log_atol`` wherever the
    reference probability is above ``significant`` (so tiny replace probabilities are checked too)."""
    actual = log_actual.double().exp()
    torch.testing.assert_close(actual, reference, atol=prob_atol, rtol=0)
    keep = reference > significant
    torch.testing.assert_close(log_actual.double()[keep], reference[keep].log(), atol=log_atol, rtol=0)


# -- log-space helpers ----------------------------------------------------------------------------


def test_log1mexp_matches_float64_reference():
    values = [-1e-10, -1e-7, -1e-3, -0.3, -math.log(2.0), -0.7, -1.0, -5.0, -20.0, -50.0]
    # 50-digit decimal arithmetic: independent of either float64 formula and of their cancellations.
    with decimal.localcontext() as context:
        context.prec = 50
        reference = torch.tensor([float((1 - decimal.Decimal(a).exp()).ln()) for a in values], dtype=torch.float64)
    torch.testing.assert_close(
        D.log1mexp(torch.tensor(values, dtype=torch.float64)), reference, rtol=1e-12, atol=1e-300
    )
    # float32: -1e-10 is where log(1 - exp(a)) gives log(0) = -inf.
    torch.testing.assert_close(
        D.log1mexp(torch.tensor(values, dtype=torch.float32)), reference.float(), rtol=2e-6, atol=1e-30
    )


def test_log1mexp_and_log_add_exp_never_leave_the_floor():
    a = torch.tensor([0.0, -1e-30, -1e-10], requires_grad=True)
    value = D.log1mexp(a)
    assert torch.isfinite(value).all() and (value >= D.LOG_ZERO).all()
    value.sum().backward()
    assert torch.isfinite(a.grad).all()
    inf = float("-inf")
    result = D.log_add_exp(
        torch.tensor([inf, inf, D.LOG_ZERO, -1e30, 0.0]), torch.tensor([inf, 0.0, D.LOG_ZERO, -1e30, 0.0])
    )
    assert torch.isfinite(result).all() and (result >= D.LOG_ZERO).all()
    torch.testing.assert_close(result[[1, 4]], torch.tensor([0.0, math.log(2.0)]))


def test_log_onehot_and_predict_x0_layout():
    codes = torch.tensor([[0, 3, K]])
    onehot = D.log_onehot(codes, K + 1)
    assert onehot.shape == (1, K + 1, 3) and onehot.dtype == torch.float32
    assert (onehot.argmax(1) == codes).all() and onehot.min() == D.LOG_ZERO
    log_x0 = D.log_predict_x0(torch.randn(2, K, L, dtype=torch.bfloat16))
    assert log_x0.shape == (2, K + 1, L) and log_x0.dtype == torch.float32
    assert (log_x0[:, K] == D.LOG_ZERO).all()
    torch.testing.assert_close(log_x0[:, :K].logsumexp(1), torch.zeros(2, L), atol=1e-6, rtol=0)


# -- schedule -------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", SCHEDULES)
def test_q_pred_rows_sum_to_one_at_every_step(name):
    schedule = D.MaskReplaceSchedule(K, T, **SCHEDULES[name])
    codes = torch.arange(K + 1).repeat(T + 1, 1)  # every x_0, MASK included
    t = torch.arange(-1, T)
    log_q = schedule.q_pred(D.log_onehot(codes, K + 1), t)
    assert torch.isfinite(log_q).all()
    torch.testing.assert_close(log_q.logsumexp(1).exp(), torch.ones(T + 1, K + 1), atol=1e-6, rtol=0)


@pytest.mark.parametrize("name", SCHEDULES)
def test_q_pred_equals_product_of_step_matrices(name):
    schedule = D.MaskReplaceSchedule(K, T, **SCHEDULES[name])
    dense = DenseProcess(K, T, SCHEDULES[name])
    x0 = torch.arange(K + 1)
    for t in range(-1, T):
        log_q = schedule.q_pred(D.log_onehot(x0.unsqueeze(0), K + 1), torch.tensor([t]))[0]  # (C, L = x0)
        assert_log_close(log_q.T, dense.between(-1, t))
    # The float64 per-step values the schedule exposes are those of the end points.
    reference = torch.tensor(per_step_float64(K, T, **SCHEDULES[name]), dtype=torch.float64)
    torch.testing.assert_close(
        torch.stack([schedule.alpha, schedule.beta, schedule.gamma], 1), reference, atol=1e-12, rtol=0
    )


def test_q_pred_of_a_distribution_is_the_mixture():
    schedule = D.MaskReplaceSchedule(K, T, **REPLACE_ENDS)
    dense = DenseProcess(K, T, REPLACE_ENDS)
    probs = torch.softmax(torch.randn(K + 1, 3, generator=gen(3), dtype=torch.float64), 0)  # MASK mass too
    for t in (0, 4, T - 1):
        log_q = schedule.q_pred(probs.log().float().unsqueeze(0), torch.tensor([t]))[0]
        assert_log_close(log_q, dense.between(-1, t).T @ probs)


def test_q_pred_one_step_is_the_likelihood_of_x_t():
    schedule = D.MaskReplaceSchedule(K, T, **REPLACE_ENDS)
    dense = DenseProcess(K, T, REPLACE_ENDS)
    x_t = torch.arange(K + 1).unsqueeze(0)
    for t in (0, 1, 6, T - 1):
        log_likelihood = schedule.q_pred_one_step(D.log_onehot(x_t, K + 1), torch.tensor([t]))[0]
        # Column j of Q_t is q(x_t = j | x_{t-1} = .).
        reference = dense.steps[t]
        assert_log_close(log_likelihood, reference, significant=1e-20)


def test_q_sample_frequencies_follow_q_pred():
    schedule = D.MaskReplaceSchedule(K, T, **REPLACE_ENDS)
    count, t = 40000, T - 1
    x0 = torch.full((1, count), 2)
    x_t = schedule.q_sample(x0, torch.tensor([t]), gen(0))
    frequencies = torch.bincount(x_t[0], minlength=K + 1).double() / count
    expected = schedule.q_pred(D.log_onehot(x0[:, :1], K + 1), torch.tensor([t]))[0, :, 0].double().exp()
    torch.testing.assert_close(frequencies, expected, atol=0.01, rtol=0)
    identity = schedule.q_sample(x0, torch.tensor([-1]), gen(0))
    assert torch.equal(identity, x0)


def test_replace_mass_of_released_and_custom_schedules():
    released = D.MaskReplaceSchedule(K, 100)
    torch.testing.assert_close(released.replace_mass(torch.arange(100)), torch.full((100,), 1e-6), rtol=1e-3, atol=0)
    custom = D.MaskReplaceSchedule(K, 100, att_T=0.0, ctt_T=0.9)
    assert custom.replace_mass(99).item() == pytest.approx(0.1, rel=1e-5)
    assert custom.replace_mass(-1).item() == 0.0


@pytest.mark.parametrize(
    "ends, named",
    [
        ({"att_T": 0.2, "ctt_T": 0.9}, "att_T + ctt_T"),
        ({"att_1": 0.5, "att_T": 0.6}, "att_T > att_1"),
        ({"ctt_1": 0.5, "ctt_T": 0.4}, "ctt_T < ctt_1"),
        ({"ctt_T": 1.5}, "ctt_T"),
        ({"att_1": 0.5, "att_T": 0.5, "ctt_1": 0.0, "ctt_T": 0.5}, "beta_t is negative"),
    ],
)
def test_invalid_end_points_are_refused(ends, named):
    with pytest.raises(ValueError, match=r"att_1=.*ctt_T=") as caught:
        D.MaskReplaceSchedule(K, T, **ends)
    assert named in str(caught.value) and "\n" not in str(caught.value)


# -- posterior ------------------------------------------------------------------------------------

POSTERIOR_PAIRS = [(0, -1), (1, 0), (5, 4), (T - 1, T - 2), (T - 1, 3), (7, -1), (9, 2)]


@pytest.mark.parametrize("name", SCHEDULES)
def test_posterior_of_onehot_x0_is_bayes_rule(name):
    schedule = D.MaskReplaceSchedule(K, T, **SCHEDULES[name])
    dense = DenseProcess(K, T, SCHEDULES[name])
    x0 = torch.randint(0, K, (1, L), generator=gen(1))
    for t, s in POSTERIOR_PAIRS:
        # Every kind of x_t: MASK, the code x_0 itself, and a replaced code (possible under both schedules).
        x_t = torch.stack([torch.full((L,), K), x0[0], (x0[0] + 1) % K]).view(3, L)
        x0_batch = x0.expand(3, L)
        t_B, s_B = torch.full((3,), t), torch.full((3,), s)
        log_post = schedule.posterior(D.log_onehot(x0_batch, K + 1), x_t, t_B, None if s == t - 1 else s_B)
        for b in range(3):
            for i in range(L):
                reference = dense.bayes(int(x0_batch[b, i]), int(x_t[b, i]), t, s)
                assert_log_close(log_post[b, :, i], reference, prob_atol=1e-5)


@pytest.mark.parametrize("name", SCHEDULES)
def test_posterior_of_predicted_x0_is_the_mixture_of_bayes_posteriors(name):
    schedule = D.MaskReplaceSchedule(K, T, **SCHEDULES[name])
    dense = DenseProcess(K, T, SCHEDULES[name])
    log_x0 = D.log_predict_x0(2.0 * torch.randn(1, K, L, generator=gen(2)))
    p_x0 = log_x0[0, :K].double().exp()  # (K, L)
    x_t = torch.randint(0, K + 1, (1, L), generator=gen(4))
    for t, s in POSTERIOR_PAIRS:
        log_post = schedule.posterior(log_x0, x_t, torch.tensor([t]), torch.tensor([s]))[0]
        for i in range(L):
            # p(x_s | x_t) = sum_k q(x_s | x_t, x_0 = k) p(x_0 = k | x_t), each Bayes posterior normalised.
            reference = sum(p_x0[k, i] * dense.bayes(k, int(x_t[0, i]), t, s) for k in range(K))
            assert_log_close(log_post[:, i], reference, prob_atol=1e-5)


@pytest.mark.parametrize("name", SCHEDULES)
def test_posterior_and_losses_stay_finite_at_the_edges(name):
    schedule = D.MaskReplaceSchedule(K, T, **SCHEDULES[name])
    x0 = torch.randint(0, K, (4, L), generator=gen(5))
    saturated = 1e4 * (
        2.0 * torch.nn.functional.one_hot(torch.randint(0, K, (4, L), generator=gen(6)), K).permute(0, 2, 1).float()
        - 1.0
    )
    for logits in (torch.randn(4, K, L), saturated):
        logits = logits.clone().requires_grad_(True)
        for t in (0, 1, T - 1):
            t_B = torch.full((4,), t)
            for x_t in (schedule.q_sample(x0, t_B, gen(t)), torch.full((4, L), K)):
                log_x0 = D.log_predict_x0(logits)
                log_post = schedule.posterior(log_x0, x_t, t_B)
                assert torch.isfinite(log_post).all()
                torch.testing.assert_close(log_post.logsumexp(1), torch.zeros(4, L), atol=1e-5, rtol=0)
                loss = D.vb_loss(log_x0, x0, x_t, t_B, schedule)
                assert torch.isfinite(loss.loss_B).all() and (loss.lt_B > -1e-5).all()
                (grad,) = torch.autograd.grad(loss.loss_B.sum(), logits)
                assert torch.isfinite(grad).all()


def test_posterior_refuses_non_forward_pairs():
    schedule = D.MaskReplaceSchedule(K, T)
    log_x0 = D.log_onehot(torch.zeros(1, L, dtype=torch.long), K + 1)
    with pytest.raises(ValueError, match="s < t"):
        schedule.posterior(log_x0, torch.zeros(1, L, dtype=torch.long), torch.tensor([3]), torch.tensor([3]))
    with pytest.raises(ValueError, match="timesteps"):
        schedule.posterior(log_x0, torch.zeros(1, L, dtype=torch.long), torch.tensor([T]))


# -- losses ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", SCHEDULES)
def test_vb_loss_is_nonnegative_and_vanishes_for_the_true_x0(name):
    schedule = D.MaskReplaceSchedule(K, T, **SCHEDULES[name])
    batch = 2 * T
    x0 = torch.randint(0, K, (batch, L), generator=gen(7))
    t_B = torch.arange(batch) % T
    x_t = schedule.q_sample(x0, t_B, gen(8))
    random_loss = D.vb_loss(D.log_predict_x0(torch.randn(batch, K, L, generator=gen(9))), x0, x_t, t_B, schedule)
    assert (random_loss.lt_B >= -1e-5).all() and (random_loss.loss_B >= -1e-5).all()
    assert random_loss.lt_B[t_B > 0].max() > 0.1  # a wrong prediction costs
    onehot_logits = 30.0 * torch.nn.functional.one_hot(x0, K).permute(0, 2, 1).float()
    exact = D.vb_loss(D.log_predict_x0(onehot_logits), x0, x_t, t_B, schedule)
    assert exact.lt_B[t_B > 0].abs().max() < 1e-4
    # The auxiliary term is KL(onehot(x_0) || p) = -sum log p(x_0) for t > 0.
    log_x0 = D.log_predict_x0(torch.randn(batch, K, L, generator=gen(10)))
    terms = D.vb_loss(log_x0, x0, x_t, t_B, schedule)
    nll = -log_x0.gather(1, x0.unsqueeze(1)).sum((1, 2))
    torch.testing.assert_close(terms.aux_B[t_B > 0], nll[t_B > 0], rtol=1e-5, atol=1e-4)
    torch.testing.assert_close(terms.lt_B[t_B == 0], terms.aux_B[t_B == 0])


def test_vb_loss_matches_masked_ce_on_a_pure_absorbing_schedule():
    # With no replace noise, and a prediction that keeps unmasked tokens (MDLM's carry-over), the step-t
    # KL of a masked token is w_t * CE and that of an unmasked one 0: the VB loss and the absorbing-state
    # loss must agree for t > 0, which checks the weight w_t against the exact posterior.
    schedule = D.MaskReplaceSchedule(K, T, att_1=0.95, att_T=0.0, ctt_1=0.05, ctt_T=1.0)
    assert (schedule.replace_mass(torch.arange(-1, T)) == 0).all()
    batch = 3 * T
    x0 = torch.randint(0, K, (batch, L), generator=gen(11))
    t_B = 1 + torch.arange(batch) % (T - 1)
    x_t = schedule.q_sample(x0, t_B, gen(12))
    logits = torch.randn(batch, K, L, generator=gen(13))
    unmasked = (x_t < K).unsqueeze(1)
    carry_over = 100.0 * torch.nn.functional.one_hot(x_t.clamp(max=K - 1), K).permute(0, 2, 1).float()
    vb = D.vb_loss(D.log_predict_x0(torch.where(unmasked, carry_over, logits)), x0, x_t, t_B, schedule).lt_B
    ce = D.masked_ce_loss(logits, x0, x_t, t_B, schedule)
    torch.testing.assert_close(vb, ce, rtol=1e-4, atol=1e-4)


def test_masked_ce_loss_ignores_unmasked_tokens_and_matches_a_hand_value():
    schedule = D.MaskReplaceSchedule(4, 10, **DEFAULT_ENDS)
    x0 = torch.tensor([[1, 2]])
    x_t = torch.tensor([[4, 2]])  # first token masked, second not
    t = torch.tensor([3])
    logits = torch.tensor([[[0.5, 3.0], [-1.0, 0.0], [2.0, 1.0], [0.0, -2.0]]])  # (1, K=4, L=2)
    loss = D.masked_ce_loss(logits, x0, x_t, t, schedule)
    gamma_bar = [DEFAULT_ENDS["ctt_1"] + s / 9 * (DEFAULT_ENDS["ctt_T"] - DEFAULT_ENDS["ctt_1"]) for s in range(10)]
    weight = (gamma_bar[3] - gamma_bar[2]) / gamma_bar[3]
    cross_entropy = -(-1.0 - math.log(math.exp(0.5) + math.exp(-1.0) + math.exp(2.0) + math.exp(0.0)))
    assert loss.item() == pytest.approx(weight * cross_entropy, rel=1e-6)
    changed = logits.clone()
    changed[0, :, 1] = torch.tensor([9.0, -9.0, -5.0, 4.0])  # the unmasked token
    assert D.masked_ce_loss(changed, x0, x_t, t, schedule).item() == loss.item()
    changed[0, :, 0] = torch.tensor([9.0, -9.0, -5.0, 4.0])  # the masked token
    assert D.masked_ce_loss(changed, x0, x_t, t, schedule).item() != pytest.approx(loss.item())
    # t = 0: gamma_bar_{-1} = 0, so the weight is 1.
    assert D.masked_ce_loss(logits, x0, x_t, torch.tensor([0]), schedule).item() == pytest.approx(cross_entropy)


# -- timestep sampler -----------------------------------------------------------------------------


def fill(sampler: D.TimestepSampler, rounds: int, big_step: int = 3) -> None:
    for _ in range(rounds):
        t_B = torch.arange(sampler.num_steps)
        sampler.update(t_B, torch.where(t_B == big_step, 10.0, 1.0))


def test_timestep_sampler_is_uniform_until_every_step_was_seen():
    sampler = D.TimestepSampler(T)
    fill(sampler, 10)  # 10 each: not yet > 10
    assert not sampler.ready
    t_B, p_B = sampler.sample(6000, gen(0))
    assert torch.allclose(p_B, torch.full((6000,), 1.0 / T))
    frequencies = torch.bincount(t_B, minlength=T).double() / 6000
    assert (frequencies - 1.0 / T).abs().max() < 0.03


def test_timestep_sampler_favours_steps_with_larger_losses():
    sampler = D.TimestepSampler(T)
    fill(sampler, 12)
    assert sampler.ready
    # E[L^2] after 12 EMA updates from 0 is L^2 (1 - 0.9^12); p_t is proportional to its root + 1e-4.
    root = math.sqrt(1.0 - 0.9**12)
    weights = torch.tensor([(10.0 if t == 3 else 1.0) * root + 1e-4 for t in range(T)], dtype=torch.float64)
    torch.testing.assert_close(sampler.probabilities().double(), weights / weights.sum(), rtol=1e-5, atol=0)
    t_B, p_B = sampler.sample(8000, gen(1))
    frequencies = torch.bincount(t_B, minlength=T).double() / 8000
    assert frequencies.argmax() == 3 and abs(frequencies[3] - weights[3] / weights.sum()) < 0.03
    torch.testing.assert_close(p_B, sampler.probabilities()[t_B])
    # Duplicates of one step in a batch enter the EMA once, as their mean square.
    before = sampler.loss_sq_T[5].item()
    sampler.update(torch.tensor([5, 5]), torch.tensor([2.0, 4.0]))
    assert sampler.loss_sq_T[5].item() == pytest.approx(0.9 * before + 0.1 * 10.0, rel=1e-6)


def test_timestep_sampler_state_round_trips():
    sampler = D.TimestepSampler(T)
    fill(sampler, 12)
    restored = D.TimestepSampler(T)
    restored.load_state_dict(sampler.state_dict())
    assert restored.ready
    assert torch.equal(restored.sample(64, gen(5))[0], sampler.sample(64, gen(5))[0])
    assert torch.equal(restored.loss_sq_T, sampler.loss_sq_T) and torch.equal(restored.count_T, sampler.count_T)


# -- guidance, truncation, Gumbel -----------------------------------------------------------------


def random_log_x0(seed: int, batch: int = 2) -> torch.Tensor:
    return D.log_predict_x0(3.0 * torch.randn(batch, K, L, generator=gen(seed)))


def test_guidance_end_points_and_stability():
    cond, null = random_log_x0(1), random_log_x0(2)
    torch.testing.assert_close(D.guided_log_x0(cond, null, 1.0), cond, atol=1e-6, rtol=0)
    torch.testing.assert_close(D.guided_log_x0(cond, null, 0.0), null, atol=1e-6, rtol=0)
    reference = torch.log_softmax(null[:, :K].double() + 3.0 * (cond[:, :K].double() - null[:, :K].double()), 1)
    torch.testing.assert_close(
        D.guided_log_x0(cond, null, 3.0)[:, :K].double(), reference.clamp_min(D.LOG_ZERO), atol=1e-4, rtol=0
    )
    extreme = cond.clone()
    extreme[:, 0] = float("-inf")
    extreme[:, 1] = -1e30
    for c, n in ((cond, null), (extreme, null), (cond.bfloat16(), null.bfloat16()), (extreme, extreme.flip(1))):
        for scale in (0.0, 1.0, 3.0, 100.0, 1e4, torch.tensor([1.0, 1e4])):
            guided = D.guided_log_x0(c, n, scale)
            assert guided.dtype == torch.float32 and torch.isfinite(guided).all()
            assert (guided[:, K] == D.LOG_ZERO).all() and guided.max() <= 0.0
            torch.testing.assert_close(guided[:, :K].logsumexp(1), torch.zeros(2, L), atol=1e-5, rtol=0)


def test_truncation():
    log_x0 = random_log_x0(3)
    assert torch.equal(D.truncate(log_x0, 1.0), log_x0)
    top1 = D.truncate(log_x0, 1e-3)
    assert torch.equal(top1[:, :K].argmax(1), log_x0[:, :K].argmax(1))
    assert ((top1[:, :K] > D.LOG_ZERO).sum(1) == 1).all()
    for r in (1e-3, 0.3, 0.85, 0.99):
        truncated = D.truncate(log_x0, r)
        torch.testing.assert_close(truncated.logsumexp(1), torch.zeros(2, L), atol=1e-6, rtol=0)
    # [0.4, 0.3, 0.2, 0.1] at r = 0.5: the mass before the second code is 0.4 < 0.5, before the third 0.7.
    probs = torch.tensor([0.3, 0.1, 0.4, 0.2] + [0.0] * (K - 4))
    log_probs = torch.cat([probs.clamp_min(1e-40).log(), torch.tensor([D.LOG_ZERO])]).view(1, K + 1, 1)
    kept = D.truncate(log_probs, 0.5)[0, :, 0].exp()
    torch.testing.assert_close(kept[:4], torch.tensor([3 / 7, 0.0, 4 / 7, 0.0]), atol=1e-6, rtol=0)


def test_gumbel_sample_is_deterministic_and_follows_the_distribution():
    log_x0 = random_log_x0(4, batch=3)
    assert torch.equal(D.gumbel_sample(log_x0, gen(0)), D.gumbel_sample(log_x0, gen(0)))
    assert not torch.equal(D.gumbel_sample(log_x0, gen(0)), D.gumbel_sample(log_x0, gen(1)))
    probs = torch.tensor([0.6, 0.3, 0.1] + [0.0] * (K - 2))
    log_probs = probs.clamp_min(1e-40).log().view(1, K + 1, 1).expand(1, K + 1, 20000)
    frequencies = torch.bincount(D.gumbel_sample(log_probs, gen(2))[0], minlength=K + 1).double() / 20000
    torch.testing.assert_close(frequencies, probs.double(), atol=0.015, rtol=0)


def test_gumbel_sample_with_per_sample_generators_ignores_the_batch():
    log_x0 = random_log_x0(5, batch=3)
    alone = D.gumbel_sample(log_x0[1:2], [gen(7)])
    in_batch = D.gumbel_sample(log_x0, [gen(3), gen(7), gen(4)])
    other_batch = D.gumbel_sample(torch.cat([log_x0[1:2], log_x0[0:1]]), [gen(7), gen(9)])
    assert torch.equal(in_batch[1], alone[0]) and torch.equal(other_batch[0], alone[0])
    with pytest.raises(ValueError, match="generators"):
        D.gumbel_sample(log_x0, [gen(1)])


# -- denoiser -------------------------------------------------------------------------------------

COND_DIM, TOKENS = 12, 3


def tiny_model(**options) -> DiffusionTransformer:
    torch.manual_seed(0)
    config = {"depth": 2, "width": 32, "heads": 4, "mlp_ratio": 2.0} | options
    return DiffusionTransformer(K, T, (4, 4), COND_DIM, **config).eval()


def denoiser_inputs(batch: int = 3, seed: int = 0):
    generator = gen(seed)
    codes = torch.randint(0, K + 1, (batch, L), generator=generator)
    t = torch.randint(0, T, (batch,), generator=generator)
    condition = torch.randn(batch, TOKENS, COND_DIM, generator=generator)
    return codes, t, condition


def test_denoiser_shapes_batch_one_and_bf16_autocast():
    model = tiny_model()
    codes, t, condition = denoiser_inputs()
    logits = model(codes, t, condition)
    assert logits.shape == (3, K, L) and logits.dtype == torch.float32 and torch.isfinite(logits).all()
    single = model(codes[1:2], t[1:2], condition[1:2])
    torch.testing.assert_close(single, logits[1:2], atol=1e-5, rtol=1e-5)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        low = model(codes, t, condition)
        cache = model.precompute_condition(condition)
    assert low.dtype == torch.float32 and torch.isfinite(low).all()
    assert torch.isfinite(model(codes, t, cache=cache)).all()  # bf16 cache outside autocast
    huge = model(codes, t, 1e6 * condition)  # tokens are L2-normalised
    torch.testing.assert_close(huge, logits, atol=1e-4, rtol=1e-4)


def _reference_attention(q, k, v, mask=None):
    """Softmax attention in float64, written out: the reference for :func:`attend`'s two paths."""
    scores = (q.double() @ k.double().transpose(-1, -2)) / math.sqrt(q.shape[-1])
    if mask is not None:
        scores = scores.masked_fill(~mask, float("-inf"))
    return scores.softmax(-1) @ v.double()


@pytest.mark.parametrize("grad", [True, False], ids=["training", "sampling"])
def test_attend_in_bf16_matches_float64_attention_with_and_without_a_mask(grad):
    """Both paths of ``attend`` under bf16 (the explicit products when gradients flow on the CPU, the
    fused kernel otherwise) agree with float64 attention to bf16's precision, values and gradients."""
    from vqtouch.plugins.generator.denoiser import attend

    generator = gen(4)
    q, k, v = (torch.randn(2, 3, 16, 8, generator=generator) for _ in range(3))
    mask = torch.rand(2, 1, 1, 16, generator=generator) > 0.4
    mask[..., 0] = True
    for key_mask in (None, mask):
        expected = _reference_attention(q, k, v, key_mask)
        leaves = [tensor.bfloat16().requires_grad_(grad) for tensor in (q, k, v)]
        with torch.set_grad_enabled(grad):
            out = attend(*leaves, key_mask)
        assert out.dtype == torch.bfloat16
        torch.testing.assert_close(out.double(), expected, atol=0.03, rtol=0.03)
        if grad:
            out.double().pow(2).sum().backward()
            reference = [tensor.double().requires_grad_() for tensor in (q, k, v)]
            _reference_attention(*reference, key_mask).pow(2).sum().backward()
            for leaf, ref in zip(leaves, reference):
                torch.testing.assert_close(leaf.grad.double(), ref.grad, atol=0.05, rtol=0.05)


def test_attend_takes_the_explicit_path_only_for_bf16_training_on_the_cpu(monkeypatch):
    from vqtouch.plugins.generator import denoiser

    fused_calls = []
    fused = denoiser.F.scaled_dot_product_attention
    monkeypatch.setattr(
        denoiser.F, "scaled_dot_product_attention", lambda *a, **kw: fused_calls.append(a[0].dtype) or fused(*a, **kw)
    )
    q = torch.randn(1, 2, 4, 8, requires_grad=True)
    denoiser.attend(q, q, q)  # fp32 training: the fused kernel
    denoiser.attend(q.bfloat16(), q.bfloat16(), q.bfloat16())  # bf16 training: explicit
    with torch.no_grad():
        denoiser.attend(q.bfloat16(), q.bfloat16(), q.bfloat16())  # bf16 sampling: the fused kernel
    assert fused_calls == [torch.float32, torch.bfloat16]
    # Too many scores to keep for the backward (a large code grid): the fused kernel, whose memory grows with L.
    monkeypatch.setattr(denoiser, "EXPLICIT_ATTENTION_MAX_SCORES", 1 * 2 * 4 * 4 - 1)
    denoiser.attend(q.bfloat16(), q.bfloat16(), q.bfloat16())
    assert fused_calls == [torch.float32, torch.bfloat16, torch.bfloat16]


def test_denoiser_in_bf16_training_keeps_padding_out_and_stays_finite():
    """Under bf16 autocast with gradients (the explicit attention), a padded token changes nothing and
    a row without real tokens stays finite, as in fp32."""
    model = tiny_model().train()
    codes, t, condition = denoiser_inputs()
    mask = torch.tensor([[True, True, False], [True, False, False], [False, False, False]])
    changed = condition.clone()
    changed[0, 2] += 5.0
    with torch.autocast("cpu", dtype=torch.bfloat16):
        masked = model(codes, t, condition, condition_mask=mask)
        moved = model(codes, t, changed, condition_mask=mask)
    assert torch.isfinite(masked).all() and masked.requires_grad
    torch.testing.assert_close(moved, masked, atol=0, rtol=0)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        loss = model(codes, t, condition, condition_mask=mask).logsumexp(1).mean()
    loss.backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


def test_denoiser_condition_cache_gives_the_same_logits():
    model = tiny_model()
    codes, t, condition = denoiser_inputs()
    mask = torch.tensor([[True, True, False], [True, False, False], [False, False, False]])
    for token_mask in (None, mask):
        cache = model.precompute_condition(condition, token_mask)
        direct = model(codes, t, condition, condition_mask=token_mask)
        torch.testing.assert_close(model(codes, t, cache=cache), direct, atol=1e-6, rtol=1e-6)
        for step in range(3):  # reused across steps
            torch.testing.assert_close(
                model(codes, (t + step) % T, cache=cache),
                model(codes, (t + step) % T, condition, condition_mask=token_mask),
                atol=1e-6,
                rtol=1e-6,
            )
    # Padding is ignored: changing a masked-out token changes nothing; a row without tokens stays finite.
    changed = condition.clone()
    changed[0, 2] += 5.0
    masked = model(codes, t, condition, condition_mask=mask)
    torch.testing.assert_close(model(codes, t, changed, condition_mask=mask), masked, atol=1e-6, rtol=1e-6)
    assert torch.isfinite(masked).all()


def test_denoiser_depends_on_condition_and_timestep():
    model = tiny_model()
    codes, t, condition = denoiser_inputs()
    logits = model(codes, t, condition)
    other_condition = model(codes, t, torch.randn(3, TOKENS, COND_DIM, generator=gen(9)))
    other_time = model(codes, (t + 1) % T, condition)
    assert (other_condition - logits).abs().amax(dim=(1, 2)).min() > 1e-4
    assert (other_time - logits).abs().amax(dim=(1, 2)).min() > 1e-4


def test_denoiser_gradient_reaches_every_parameter():
    model = tiny_model(dropout=0.1).train()
    codes, t, condition = denoiser_inputs(batch=4)
    codes[:, : K + 1] = torch.arange(K + 1)  # every token embedding row
    grid = torch.randn(4, COND_DIM, 4, 4, generator=gen(2))  # an aligned condition image's map: the grid path
    logits = model(codes, t, condition, condition_mask=torch.tensor([[True, True, False]] * 4), condition_grid=grid)
    (logits * torch.randn(logits.shape, generator=gen(1))).sum().backward()
    for name, parameter in model.named_parameters():
        assert parameter.grad is not None, name
        assert torch.isfinite(parameter.grad).all() and parameter.grad.abs().sum() > 0, name


def test_denoiser_rejects_bad_inputs():
    model = tiny_model()
    codes, t, condition = denoiser_inputs()
    with pytest.raises(ValueError, match="exactly one"):
        model(codes, t)
    with pytest.raises(ValueError, match="grid"):
        model(codes[:, :10], t, condition)
    with pytest.raises(ValueError, match="divisible"):
        DiffusionTransformer(K, T, (4, 4), COND_DIM, width=30, heads=4)

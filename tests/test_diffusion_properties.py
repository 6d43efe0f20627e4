"""Property-based tests (hypothesis) of the discrete-diffusion maths in vqtouch.plugins.generator.diffusion.

Every reference here is float64 and built by the test itself, never from the module's tables:

- the schedule: per-step alpha_t, gamma_t from the linear cumulative end points, then cumulative
  products alpha_bar_{t|s} = prod alpha_i, 1 - gamma_bar_{t|s} = prod (1 - gamma_i) and
  beta_bar_{t|s} = (1 - alpha_bar - gamma_bar) / K (docs/diffusion.md section 1);
- q(x_t | x_0): the closed form alpha_bar 1[j = k] + beta_bar (codes), gamma_bar (MASK), applied to a
  one-hot or a soft x_0;
- q(x_s | x_t, x_0): Bayes' rule on explicit (K+1) x (K+1) step matrices multiplied out (small K), or on
  the closed-form rows and columns of those matrices (any K, one-hot x_0).

Draws cover K in {1, 2, 16384} plus small K, T from 2 to 1000, end points over the whole valid range
(the config's bounds, att_T + ctt_T <= 1 at both ends and a non-negative replace probability at every
step) including the released schedule and the corners (identity first step, everything masked at the
end, pure replace, pure mask), every (t, s) with -1 <= s < t (skips, s = -1, t = 0, t = T - 1), batch
sizes 1-3 and grids 1x1 to 4x4.

Examples are derandomised and there is no example database, so a run is reproducible (see
PROPERTY_SCALE for a deeper random search).
"""

from __future__ import annotations

import math
import os

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from vqtouch.plugins.generator import diffusion as D

LOG_ZERO = -70.0

#: fp32 log-space maths against a float64 reference: absolute error of a probability.
PROB_ATOL = 2e-5
#: ... and error of a log-probability where the reference probability is above LOG_SIGNIFICANT.
LOG_ATOL = 2e-3
LOG_SIGNIFICANT = 1e-7
#: A posterior is compared with Bayes' rule only where its denominator q(x_t | x_0) is at least this
#: (below it, q(x_t | x_0) is float64 rounding of a zero or under the module's exp(-70) floor, and
#: Bayes' rule divides noise by noise).
BAYES_MIN = 1e-9
#: A soft x_0 entry below this may be dropped from the reference when x_t is impossible from it.
NEGLIGIBLE_P = 1e-12
ROW_SUM_ATOL = 2e-5


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """One intra-op thread: these tensors are small, and on a loaded 2-core machine torch's thread pool
    makes a T = 100 schedule take 100x longer.  Restored afterwards."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


#: VQTOUCH_PROPERTY_SCALE=N multiplies every test's number of examples by N and draws them at random
#: (a deeper, non-reproducible search, for local use); unset, the examples are the same on every run.
PROPERTY_SCALE = float(os.environ.get("VQTOUCH_PROPERTY_SCALE", "1"))


def _settings(examples: int):
    return settings(
        max_examples=max(1, round(examples * PROPERTY_SCALE)),
        deadline=None,
        derandomize=PROPERTY_SCALE == 1,
        database=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    )


# -- strategies -----------------------------------------------------------------------------------

DEFAULT_ENDS = {"att_1": 0.99999, "att_T": 0.000009, "ctt_1": 0.000009, "ctt_T": 0.99999}
CORNER_ENDS = [
    DEFAULT_ENDS,
    {"att_1": 0.99, "att_T": 0.05, "ctt_1": 0.005, "ctt_T": 0.9},  # real replace noise
    {"att_1": 1.0, "att_T": 0.0, "ctt_1": 0.0, "ctt_T": 1.0},  # identity first step, all MASK at the end
    {"att_1": 1.0, "att_T": 0.0, "ctt_1": 0.0, "ctt_T": 0.0},  # pure replace: uniform codes at the end
    {"att_1": 1.0, "att_T": 1.0, "ctt_1": 0.0, "ctt_T": 0.0},  # the identity at every step
    {"att_1": 0.95, "att_T": 0.0, "ctt_1": 0.05, "ctt_T": 1.0},  # pure mask
    {"att_1": 1e-9, "att_T": 0.0, "ctt_1": 0.0, "ctt_T": 0.5},  # nearly all replaced at t = 0
    {"att_1": 0.5, "att_T": 0.5, "ctt_1": 0.0, "ctt_T": 0.0},  # one replace step, then identity
    {"att_1": 0.99999, "att_T": 0.0, "ctt_1": 0.000009, "ctt_T": 0.99999},
]

_UNIT = st.one_of(st.sampled_from([0.0, 1.0, 0.5]), st.floats(0.0, 1.0))


@st.composite
def end_points(draw) -> dict[str, float]:
    """Valid (att_1, att_T, ctt_1, ctt_T): a corner, or drawn over the whole valid region.

    The region: 0 < att_1 <= 1 - ctt_1, 0 <= ctt_1 < 1, ctt_1 <= ctt_T <= 1, and
    0 <= att_T <= att_1 (1 - ctt_T) / (1 - ctt_1).  The last bound is exactly "beta_t >= 0 at every
    step": with both cumulative values linear in t, alpha_bar_t / (1 - gamma_bar_t) is a linear-fractional
    function of t, hence monotone, and beta_{t|s} >= 0 for all s < t iff it does not increase, i.e. iff
    its value at t = T-1 is at most its value at t = 0.

    ctt_1 reaches 0.999999, where computing 1 - gamma_bar by cancellation once refused valid pure-mask
    schedules (see test_valid_pure_mask_schedule_with_ctt_1_near_1_is_accepted).
    """
    if draw(st.booleans()):
        return dict(draw(st.sampled_from(CORNER_ENDS)))
    ctt_1 = draw(st.one_of(st.sampled_from([0.0, 9e-6, 0.5, 0.9999, 0.999999]), st.floats(0.0, 0.999999)))
    att_1 = (1.0 - ctt_1) * draw(st.one_of(st.just(1.0), st.floats(1e-6, 1.0)))
    ctt_T = min(1.0, ctt_1 + (1.0 - ctt_1) * draw(_UNIT))
    att_T = min(att_1, att_1 * (1.0 - ctt_T) / (1.0 - ctt_1) * draw(_UNIT))
    return {"att_1": att_1, "att_T": att_T, "ctt_1": ctt_1, "ctt_T": ctt_T}


ANY_K = st.one_of(st.sampled_from([1, 2, 16384]), st.integers(1, 12))
SMALL_K = st.one_of(st.sampled_from([1, 2]), st.integers(1, 9))
STEPS = st.one_of(st.sampled_from([2, 3, 100, 1000]), st.integers(2, 40))
SMALL_STEPS = st.one_of(st.sampled_from([2, 3, 100]), st.integers(2, 30))
BATCH = st.integers(1, 3)
GRID = st.integers(1, 4)  # L = grid * grid tokens, 1x1 included
SEED = st.integers(0, 2**31 - 1)


def step_of(num_steps: int, low: int = -1) -> st.SearchStrategy[int]:
    """A timestep in [low, T-1], the ends more often than uniform."""
    return st.one_of(
        st.sampled_from(sorted({low, max(low, 0), min(1, num_steps - 1), num_steps - 1})),
        st.integers(low, num_steps - 1),
    )


@st.composite
def step_pairs(draw, num_steps: int, batch: int) -> list[tuple[int, int]]:
    """(t, s) per sample with 0 <= t <= T-1 and -1 <= s < t: single steps, skips, s = -1, t = T-1."""
    pairs = []
    for _ in range(batch):
        t = draw(step_of(num_steps, low=0))
        s = draw(st.one_of(st.sampled_from(sorted({-1, t - 1, min(0, t - 1)})), st.integers(-1, t - 1)))
        pairs.append((t, s))
    return pairs


def gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


# -- independent float64 reference of the forward process -----------------------------------------


class Reference:
    """The mask-and-replace process in float64 numpy, from the end points alone (docs/diffusion.md section 1)."""

    def __init__(self, num_codes: int, num_steps: int, att_1: float, att_T: float, ctt_1: float, ctt_T: float) -> None:
        self.K, self.T = num_codes, num_steps
        self._products: dict[tuple[int, int], np.ndarray] = {}
        fraction = np.arange(num_steps, dtype=np.float64) / (num_steps - 1)
        alpha_bar = att_1 + fraction * (att_T - att_1)
        gamma_bar = ctt_1 + fraction * (ctt_T - ctt_1)
        previous_alpha = np.concatenate([[1.0], alpha_bar[:-1]])
        previous_gamma = np.concatenate([[0.0], gamma_bar[:-1]])
        self.alpha = alpha_bar / previous_alpha  # > 0 denominators: only t = T-1 may hit 0
        self.gamma = 1.0 - (1.0 - gamma_bar) / (1.0 - previous_gamma)
        self.beta = np.clip(1.0 - self.alpha - self.gamma, 0.0, None) / num_codes

    def cumulative(self, s: int, t: int) -> tuple[float, float, float]:
        """(alpha_bar, beta_bar, gamma_bar) of the transition from step s to step t (s = -1: from x_0)."""
        alpha = float(np.prod(self.alpha[s + 1 : t + 1]))
        keep = float(np.prod(1.0 - self.gamma[s + 1 : t + 1]))
        return alpha, max(keep - alpha, 0.0) / self.K, 1.0 - keep

    def step_matrix(self, t: int) -> np.ndarray:
        """Q_t[k, j] = q(x_t = j | x_{t-1} = k), MASK = K absorbing."""
        K = self.K
        matrix = np.zeros((K + 1, K + 1))
        matrix[:K, :K] = self.beta[t] + self.alpha[t] * np.eye(K)
        matrix[:K, K] = self.gamma[t]
        matrix[K, K] = 1.0
        return matrix

    def between(self, s: int, t: int) -> np.ndarray:
        """Q_{s+1} ... Q_t as a dense (K+1) x (K+1) matrix (the identity for s = t)."""
        if (s, t) not in self._products:
            matrix = np.eye(self.K + 1)
            for step in range(s + 1, t + 1):
                matrix = matrix @ self.step_matrix(step)
            self._products[s, t] = matrix
        return self._products[s, t]


def reference_q_pred(ref: Reference, probs_BCL: np.ndarray, t_list: list[int]) -> np.ndarray:
    """sum_k p(k) q(x_t = . | x_0 = k) in closed form, float64 (B, C, L)."""
    K = ref.K
    out = np.empty_like(probs_BCL)
    for b, t in enumerate(t_list):
        alpha, beta, gamma = ref.cumulative(-1, t)
        code_mass = probs_BCL[b, :K].sum(axis=0, keepdims=True)
        out[b, :K] = alpha * probs_BCL[b, :K] + beta * code_mass
        out[b, K] = gamma * code_mass[0] + probs_BCL[b, K]
    return out


def dense_posterior(ref: Reference, p_K: np.ndarray, x_t: int, s: int, t: int) -> np.ndarray | None:
    """sum_k p(k) q(x_s | x_t, x_0 = k) / sum_k p(k) by Bayes' rule on dense matrices (C,), or None where
    it is undefined (x_t impossible, up to BAYES_MIN, from an x_0 that p does not rule out)."""
    m_0s, m_st, m_0t = ref.between(-1, s), ref.between(s, t), ref.between(-1, t)
    K = ref.K
    denominators = m_0t[:K, x_t]
    possible = denominators >= BAYES_MIN
    if (p_K[~possible] > NEGLIGIBLE_P).any():
        return None
    joint_KC = m_0s[:K, :] * m_st[:, x_t][None, :]  # q(x_s | x_0 = k) q(x_t | x_s)
    bayes_KC = joint_KC[possible] / denominators[possible, None]
    mixture = (p_K[possible, None] * bayes_KC).sum(axis=0)
    return mixture / mixture.sum()


def closed_form_posterior(ref: Reference, x0: int, x_t: int, s: int, t: int) -> np.ndarray | None:
    """q(x_s | x_t, x_0) for a one-hot x_0 from the closed-form row q(x_s | x_0) and column q(x_t | x_s)
    of the transition matrices, O(K) (C,); None where q(x_t | x_0) < BAYES_MIN."""
    K = ref.K
    a_s, b_s, g_s = ref.cumulative(-1, s)
    a_ts, b_ts, g_ts = ref.cumulative(s, t)
    row = np.full(K + 1, b_s)
    row[x0] += a_s
    row[K] = g_s
    column = np.zeros(K + 1)
    if x_t == K:
        column[:K], column[K] = g_ts, 1.0
    else:
        column[:K] = b_ts
        column[x_t] += a_ts
    joint = row * column
    denominator = joint.sum()
    a_t, b_t, g_t = ref.cumulative(-1, t)
    # Chapman-Kolmogorov inside the reference itself: the two ways to q(x_t | x_0) agree.
    direct = g_t if x_t == K else b_t + (a_t if x_t == x0 else 0.0)
    assert abs(denominator - direct) <= 1e-12 + 1e-9 * direct
    return None if denominator < BAYES_MIN else joint / denominator


# -- assertions -----------------------------------------------------------------------------------


def assert_valid_log_probs(log_BCL: torch.Tensor, normalised: bool = True) -> None:
    """Finite, within [LOG_ZERO, 0], and (if normalised) every token's classes sum to 1 in float64."""
    assert log_BCL.dtype == torch.float32
    assert torch.isfinite(log_BCL).all(), "NaN/Inf in the output"
    assert log_BCL.min() >= LOG_ZERO and log_BCL.max() <= 0.0
    if normalised:
        sums = log_BCL.double().exp().sum(dim=1)
        worst = (sums - 1.0).abs().max().item()
        assert worst <= ROW_SUM_ATOL, f"a row sums to 1 +- {worst:.3g}"


def assert_matches(log_actual: torch.Tensor, reference: np.ndarray, what: str) -> None:
    """Probabilities within PROB_ATOL; logs within LOG_ATOL where the reference is significant."""
    actual = log_actual.double().exp().numpy()
    error = np.abs(actual - reference)
    worst = np.unravel_index(np.argmax(error), error.shape)
    assert error.max() <= PROB_ATOL, (
        f"{what}: probability {actual[worst]:.9g} vs reference {reference[worst]:.9g} at {worst}"
    )
    keep = reference > LOG_SIGNIFICANT
    log_error = np.abs(log_actual.double().numpy()[keep] - np.log(reference[keep]))
    assert log_error.size == 0 or log_error.max() <= LOG_ATOL, f"{what}: log error {log_error.max():.3g}"


def log_onehot_BCL(codes_BL: torch.Tensor, num_classes: int) -> torch.Tensor:
    """One-hot in log space built here (0 at the code, LOG_ZERO elsewhere), float32 (B, C, L)."""
    out = torch.full((codes_BL.shape[0], num_classes, codes_BL.shape[1]), LOG_ZERO)
    return out.scatter_(1, codes_BL.unsqueeze(1), 0.0)


def soft_log_x0(seed: int, batch: int, num_codes: int, length: int, scale: float, mask_mass: bool) -> torch.Tensor:
    """log_softmax of scaled Gaussian logits over the codes (and MASK too when ``mask_mass``), float32
    (B, K+1, L); without MASK mass the MASK row is LOG_ZERO as the network's prediction has it."""
    # Normalised in float64, then rounded: a float32 log_softmax over 16385 classes is itself off by ~3e-5.
    logits = scale * torch.randn(batch, num_codes + 1, length, generator=gen(seed), dtype=torch.float64)
    if mask_mass:
        return torch.log_softmax(logits, dim=1).clamp(LOG_ZERO, 0.0).float()
    codes = torch.log_softmax(logits[:, :num_codes], dim=1).clamp(LOG_ZERO, 0.0)
    return torch.cat([codes, torch.full_like(codes[:, :1], LOG_ZERO)], dim=1).float()


def draw_x_t(draw, x0_BL: torch.Tensor, num_codes: int) -> torch.Tensor:
    """x_t per token: MASK, x_0 itself, or another code (a replacement); sometimes all MASK."""
    if draw(st.integers(0, 3), label="all masked if 0") == 0:
        return torch.full_like(x0_BL, num_codes)
    flat = x0_BL.flatten().tolist()
    kinds = draw(st.lists(st.sampled_from(["mask", "same", "other"]), min_size=len(flat), max_size=len(flat)))
    offset = draw(st.integers(1, max(1, num_codes - 1)))
    out = [
        num_codes if kind == "mask" else code if kind == "same" or num_codes == 1 else (code + offset) % num_codes
        for kind, code in zip(kinds, flat)
    ]
    return torch.tensor(out).view_as(x0_BL)


# -- 1. q(x_t | x_0) ------------------------------------------------------------------------------


@_settings(40)
@given(num_codes=ANY_K, num_steps=STEPS, ends=end_points(), batch=BATCH, grid=GRID, data=st.data())
def test_q_pred_rows_are_distributions_matching_the_closed_form(num_codes, num_steps, ends, batch, grid, data):
    """q_pred of a one-hot x_0 (MASK included as x_0) and of a soft x_0 (with MASK mass) at any t in
    [-1, T-1]: finite, in [LOG_ZERO, 0], rows sum to 1, and equal to the float64 closed form."""
    schedule = D.MaskReplaceSchedule(num_codes, num_steps, **ends)
    ref = Reference(num_codes, num_steps, **ends)
    length, C = grid * grid, num_codes + 1
    t_list = data.draw(st.lists(step_of(num_steps), min_size=batch, max_size=batch), label="t")
    t_B = torch.tensor(t_list)
    codes = data.draw(st.lists(st.integers(0, num_codes), min_size=batch * length, max_size=batch * length))
    x0_BL = torch.tensor(codes).view(batch, length)
    onehot = log_onehot_BCL(x0_BL, C)
    exact_onehot = np.zeros((batch, C, length))
    np.put_along_axis(exact_onehot, x0_BL.numpy()[:, None, :], 1.0, axis=1)
    scale = data.draw(st.sampled_from([0.0, 1.0, 5.0, 30.0]), label="logit scale")
    soft = soft_log_x0(data.draw(SEED, label="seed"), batch, num_codes, length, scale, mask_mass=True)

    for log_x0, probs in ((onehot, exact_onehot), (soft, soft.double().exp().numpy())):
        log_q = schedule.q_pred(log_x0, t_B)
        assert log_q.shape == (batch, C, length)
        assert_valid_log_probs(log_q)
        assert_matches(log_q, reference_q_pred(ref, probs, t_list), "q(x_t | x_0)")
    # t = -1 is no noise: q(x_{-1} | x_0) = x_0.
    identity = schedule.q_pred(soft, torch.full((batch,), -1))
    torch.testing.assert_close(identity.double().exp(), soft.double().exp(), atol=1e-6, rtol=0)


@_settings(25)
@given(num_codes=SMALL_K, num_steps=SMALL_STEPS, ends=end_points(), data=st.data())
def test_q_pred_one_step_is_a_column_of_the_step_matrix(num_codes, num_steps, ends, data):
    """The posterior's likelihood factor q(x_t | x_{t-1} = .) for every x_t equals column x_t of the
    dense one-step matrix Q_t."""
    schedule = D.MaskReplaceSchedule(num_codes, num_steps, **ends)
    ref = Reference(num_codes, num_steps, **ends)
    t = data.draw(step_of(num_steps, low=0), label="t")
    x_t = torch.arange(num_codes + 1).unsqueeze(0)  # every x_t, one token each
    likelihood = schedule.q_pred_one_step(log_onehot_BCL(x_t, num_codes + 1), torch.tensor([t]))[0]
    assert_valid_log_probs(likelihood.unsqueeze(0), normalised=False)
    # likelihood[k, j] = q(x_t = j | x_{t-1} = k) = Q_t[k, j]
    assert_matches(likelihood, ref.step_matrix(t), "q(x_t | x_{t-1})")


def draw_posterior_case(data, num_codes, num_steps, batch, length):
    """A drawn posterior query: (t, s) pairs per row (and as tensors), codes x_0 (B, L) and an x_t
    (B, L) mixing MASK, x_0 and replaced codes."""
    pairs = data.draw(step_pairs(num_steps, batch), label="(t, s)")
    t_B, s_B = torch.tensor([t for t, _ in pairs]), torch.tensor([s for _, s in pairs])
    codes = data.draw(st.lists(st.integers(0, num_codes - 1), min_size=batch * length, max_size=batch * length))
    x0_BL = torch.tensor(codes).view(batch, length)
    return pairs, t_B, s_B, x0_BL, draw_x_t(data.draw, x0_BL, num_codes)


# -- 2. the posterior q(x_s | x_t, x_0) ----------------------------------------------------------


@_settings(40)
@given(num_codes=SMALL_K, num_steps=SMALL_STEPS, ends=end_points(), batch=BATCH, grid=GRID, data=st.data())
def test_posterior_is_bayes_rule_on_dense_matrices(num_codes, num_steps, ends, batch, grid, data):
    """posterior(x_0, x_t, t, s) for one-hot and soft x_0, single steps and skips (s = t-1, s < t-1,
    s = -1, t = 0, t = T-1), x_t MASK / = x_0 / replaced / all MASK: rows sum to 1 and equal
    sum_k p(k) Q_{0->s}[k, x_s] Q_{s->t}[x_s, x_t] / Q_{0->t}[k, x_t] (normalised by sum_k p(k)) with
    the Q's explicit float64 products of step matrices."""
    schedule = D.MaskReplaceSchedule(num_codes, num_steps, **ends)
    ref = Reference(num_codes, num_steps, **ends)
    length, C = grid * grid, num_codes + 1
    pairs, t_B, s_B, x0_BL, x_t_BL = draw_posterior_case(data, num_codes, num_steps, batch, length)
    scale = data.draw(st.sampled_from([0.0, 0.5, 2.0, 8.0]), label="logit scale")
    soft = soft_log_x0(data.draw(SEED, label="seed"), batch, num_codes, length, scale, mask_mass=False)

    # s defaults to t - 1: the same as passing it.
    default_s = schedule.posterior(soft, x_t_BL, t_B)
    torch.testing.assert_close(default_s, schedule.posterior(soft, x_t_BL, t_B, t_B - 1), atol=0, rtol=0)

    for log_x0, is_onehot in ((log_onehot_BCL(x0_BL, C), True), (soft, False)):
        log_post = schedule.posterior(log_x0, x_t_BL, t_B, s_B)
        assert log_post.shape == (batch, C, length)
        assert_valid_log_probs(log_post)
        p_BKL = log_x0[:, :num_codes].double().exp().numpy()
        for b, (t, s) in enumerate(pairs):
            for position in range(length):
                x_t = int(x_t_BL[b, position])
                if is_onehot:
                    p_K = np.zeros(num_codes)
                    p_K[int(x0_BL[b, position])] = 1.0
                else:
                    p_K = p_BKL[b, :, position]
                reference = dense_posterior(ref, p_K, x_t, s, t)
                if reference is None:
                    continue
                assert_matches(
                    log_post[b, :, position],
                    reference,
                    f"q(x_{s} | x_{t} = {x_t}, x_0) ({'one-hot' if is_onehot else 'soft'}, b={b})",
                )


@_settings(30)
@given(num_codes=ANY_K, num_steps=STEPS, ends=end_points(), batch=BATCH, grid=GRID, data=st.data())
def test_posterior_of_onehot_x0_matches_closed_form_bayes_for_any_k(num_codes, num_steps, ends, batch, grid, data):
    """The same Bayes rule for K up to 16384 (one-hot x_0), with the rows of Q_{0->s} and columns of
    Q_{s->t} written in closed form from the cumulative products instead of dense matrices."""
    schedule = D.MaskReplaceSchedule(num_codes, num_steps, **ends)
    ref = Reference(num_codes, num_steps, **ends)
    length, C = grid * grid, num_codes + 1
    pairs, t_B, s_B, x0_BL, x_t_BL = draw_posterior_case(data, num_codes, num_steps, batch, length)
    log_post = schedule.posterior(log_onehot_BCL(x0_BL, C), x_t_BL, t_B, s_B)
    assert_valid_log_probs(log_post)
    for b, (t, s) in enumerate(pairs):
        for position in range(length):
            reference = closed_form_posterior(ref, int(x0_BL[b, position]), int(x_t_BL[b, position]), s, t)
            if reference is not None:
                assert_matches(log_post[b, :, position], reference, f"q(x_{s} | x_{t}, x_0) K={num_codes} b={b}")


@_settings(25)
@given(num_codes=SMALL_K, num_steps=SMALL_STEPS, ends=end_points(), data=st.data())
def test_posterior_averaged_over_x_t_is_q_of_x_s(num_codes, num_steps, ends, data):
    """Self-consistency of the module alone: sum_{x_t} q(x_t | x_0) q(x_s | x_t, x_0) = q(x_s | x_0) for
    every one-hot x_0 and every s < t (impossible x_t get weight 0, so their outputs only need to be
    finite)."""
    schedule = D.MaskReplaceSchedule(num_codes, num_steps, **ends)
    t, s = data.draw(step_pairs(num_steps, 1), label="(t, s)")[0]
    C = num_codes + 1
    # Token (x_0 = k, x_t = j) for every code k and every state j: L = K (K + 1) tokens of one sample.
    x0 = torch.arange(num_codes).repeat_interleave(C).unsqueeze(0)
    x_t = torch.arange(C).repeat(num_codes).unsqueeze(0)
    post = schedule.posterior(log_onehot_BCL(x0, C), x_t, torch.tensor([t]), torch.tensor([s]))[0]
    assert_valid_log_probs(post.unsqueeze(0))
    codes = torch.arange(num_codes).unsqueeze(0)
    q_t = schedule.q_pred(log_onehot_BCL(codes, C), torch.tensor([t]))[0].double().exp()  # (C, K): [j, k]
    q_s = schedule.q_pred(log_onehot_BCL(codes, C), torch.tensor([s]))[0].double().exp()
    weights = q_t.T.reshape(1, -1)  # token (k, j)
    mixed = (post.double().exp() * weights).view(C, num_codes, C).sum(dim=2)  # [x_s, k]
    torch.testing.assert_close(mixed, q_s, atol=5e-5, rtol=0)


# -- 3. no NaN / Inf at the extremes -------------------------------------------------------------


@_settings(40)
@given(
    num_codes=ANY_K,
    num_steps=STEPS,
    ends=st.one_of(st.sampled_from(CORNER_ENDS), end_points()),
    batch=BATCH,
    grid=GRID,
    data=st.data(),
)
def test_no_nan_or_inf_at_the_extremes(num_codes, num_steps, ends, batch, grid, data):
    """q_pred, q_pred_one_step and posterior (and the posterior's gradient with respect to the network's
    logits) stay finite, in [LOG_ZERO, 0] and normalised for: all-MASK x_t, x_t that is impossible
    (a code after everything was masked, a replaced code without replace noise), t = 0 / t = T-1, s = -1,
    corner schedules, extreme or -inf x_0 predictions."""
    schedule = D.MaskReplaceSchedule(num_codes, num_steps, **ends)
    length, C = grid * grid, num_codes + 1
    pairs = data.draw(step_pairs(num_steps, batch), label="(t, s)")
    t_B, s_B = torch.tensor([t for t, _ in pairs]), torch.tensor([s for _, s in pairs])
    seed = data.draw(SEED, label="seed")
    x0_BL = torch.randint(0, num_codes, (batch, length), generator=gen(seed))
    x_t_BL = data.draw(st.sampled_from(["all mask", "all codes", "mixed"]), label="x_t")
    x_t_BL = {
        "all mask": torch.full_like(x0_BL, num_codes),
        "all codes": torch.randint(0, num_codes, (batch, length), generator=gen(seed + 1)),
        "mixed": torch.randint(0, C, (batch, length), generator=gen(seed + 2)),
    }[x_t_BL]
    scale = data.draw(st.sampled_from([0.0, 1.0, 100.0, 1e4]), label="logit scale")
    # The network's prediction (normalised in float64, then rounded to float32 as the module receives it).
    logits = scale * torch.randn(batch, num_codes, length, generator=gen(seed + 3), dtype=torch.float64)
    logits.requires_grad_(True)
    mask_row = torch.full((batch, 1, length), LOG_ZERO)
    log_pred = torch.cat([torch.log_softmax(logits, dim=1).float(), mask_row], dim=1)
    # A prediction with -inf entries (code 0 ruled out), still normalised over the codes.
    inf_logits = logits.detach().clone()
    if num_codes > 1:
        inf_logits[:, 0] = float("-inf")
    with_inf = torch.cat([torch.log_softmax(inf_logits, dim=1).float(), mask_row], dim=1)

    for log_x0 in (log_onehot_BCL(x0_BL, C), log_pred, with_inf):
        assert_valid_log_probs(schedule.q_pred(log_x0, t_B))
        assert_valid_log_probs(schedule.q_pred(log_x0, s_B))
        assert_valid_log_probs(schedule.posterior(log_x0, x_t_BL, t_B, s_B))
        assert_valid_log_probs(schedule.posterior(log_x0, x_t_BL, t_B))
    assert_valid_log_probs(schedule.q_pred_one_step(log_onehot_BCL(x_t_BL, C), t_B), normalised=False)
    post = schedule.posterior(log_pred, x_t_BL, t_B, s_B)
    (post * torch.randn(post.shape, generator=gen(seed + 4))).sum().backward()
    assert torch.isfinite(logits.grad).all(), "NaN/Inf gradient through the posterior"


# -- 4. other invariants --------------------------------------------------------------------------


@pytest.mark.parametrize("num_codes, num_steps, ctt_1", [(8, 1000, 0.999999), (1, 100, 0.999999), (1, 1000, 0.99999)])
def test_valid_pure_mask_schedule_with_ctt_1_near_1_is_accepted(num_codes, num_steps, ctt_1):
    """att_1 = 1 - ctt_1 (exactly, in float64) and att_T = 0, ctt_T = 1: no replace noise at either end,
    so beta_t = 0 at every step in exact arithmetic; the schedule is valid and must be accepted (1 - gamma_bar
    taken by cancellation once refused these: beta_t came out near -3e-9)."""
    att_1 = 1.0 - ctt_1
    assert att_1 + ctt_1 == 1.0
    schedule = D.MaskReplaceSchedule(num_codes, num_steps, att_1=att_1, att_T=0.0, ctt_1=ctt_1, ctt_T=1.0)
    assert float(schedule.beta.abs().max()) < 1e-9


@_settings(30)
@given(
    num_codes=ANY_K,
    batch=BATCH,
    grid=GRID,
    seed=SEED,
    scale=st.sampled_from([0.1, 1.0, 5.0, 40.0]),
    r=st.one_of(st.sampled_from([0.0, 1e-6, 0.5, 0.85, 0.999999, 1.0, 2.0]), st.floats(0.0, 1.0)),
)
def test_truncation_keeps_a_normalised_top_prefix(num_codes, batch, grid, seed, scale, r):
    """truncate(x_0, r): rows normalised, MASK row LOG_ZERO, the argmax always kept, the kept codes are
    the most probable ones (every kept code at least as probable as every dropped one) and keep their
    relative probabilities; the mass before the least probable kept code is < r and the kept mass is
    >= r (the smallest such prefix); r >= 1 is the identity."""
    length = grid * grid
    log_x0 = soft_log_x0(seed, batch, num_codes, length, scale, mask_mass=False)
    out = D.truncate(log_x0, r)
    assert_valid_log_probs(out)
    assert (out[:, num_codes] == LOG_ZERO).all()
    if r >= 1.0:
        assert torch.equal(out, log_x0)
        return
    codes_in, codes_out = log_x0[:, :num_codes], out[:, :num_codes]
    kept = codes_out > LOG_ZERO
    top = codes_in.argmax(dim=1, keepdim=True)
    assert kept.gather(1, top).all(), "the most probable code was dropped"
    assert torch.equal(codes_out.gather(1, top), codes_out.amax(dim=1, keepdim=True))
    lowest_kept = torch.where(kept, codes_in, torch.inf).amin(dim=1)
    highest_dropped = torch.where(kept, -torch.inf, codes_in).amax(dim=1)
    assert (highest_dropped <= lowest_kept).all(), "a dropped code is more probable than a kept one"
    shift = torch.where(kept, codes_out - codes_in, torch.nan)
    spread = shift.nan_to_num(nan=-1e9).amax(1) - shift.nan_to_num(nan=1e9).amin(1)
    assert (spread <= 1e-4).all(), "kept codes were not renormalised by one common factor"
    # Mass strictly before the least probable kept code (float64) is below r, up to the rounding of the
    # module's float32 cumulative sum over K codes (bounded by K float32 epsilons).
    tolerance = 1e-6 + num_codes * torch.finfo(torch.float32).eps
    probs = codes_in.double().exp()
    smallest_kept = torch.where(kept, probs, torch.inf).amin(1)
    mass_before = torch.where(kept, probs, 0.0).sum(1) - smallest_kept
    assert ((mass_before < r + tolerance) | (kept.sum(1) == 1)).all(), "kept more codes than needed to reach r"
    # ... and enough of them: the kept mass reaches r (the code that crosses r is kept).
    kept_mass = torch.where(kept, probs, 0.0).sum(1)
    assert (kept_mass >= r - tolerance).all(), "dropped the code whose mass crosses r"


@_settings(30)
@given(
    num_codes=ANY_K,
    batch=BATCH,
    grid=GRID,
    seed=SEED,
    scale=st.sampled_from([0.1, 1.0, 8.0, 60.0]),
    guidance=st.one_of(st.sampled_from([0.0, 1.0, 20.0]), st.floats(0.0, 20.0)),
)
def test_guided_log_x0_is_normalised_and_matches_float64(num_codes, batch, grid, seed, scale, guidance):
    """guided_log_x0: normalised over the codes, MASK row LOG_ZERO, finite; equal to the float64
    log_softmax of (1 - s) log p_null + s log p_cond; s = 0 gives p_null and s = 1 gives p_cond."""
    length = grid * grid
    cond = soft_log_x0(seed, batch, num_codes, length, scale, mask_mass=False)
    null = soft_log_x0(seed + 1, batch, num_codes, length, scale, mask_mass=False)
    out = D.guided_log_x0(cond, null, guidance)
    assert_valid_log_probs(out)
    assert (out[:, num_codes] == LOG_ZERO).all()
    mixed = (1.0 - guidance) * null[:, :num_codes].double() + guidance * cond[:, :num_codes].double()
    reference = torch.log_softmax(mixed, dim=1).exp()
    torch.testing.assert_close(out[:, :num_codes].double().exp(), reference, atol=1e-4, rtol=0)
    if guidance in (0.0, 1.0):
        expected = null if guidance == 0.0 else cond
        # Up to the float32 renormalisation over K codes (a logsumexp off by ~5e-6 at K = 16384).
        torch.testing.assert_close(out.double().exp(), expected.double().exp(), atol=1e-5, rtol=0)
    per_sample = D.guided_log_x0(cond, null, torch.full((batch,), float(guidance)))
    torch.testing.assert_close(per_sample, out, atol=0, rtol=0)


@_settings(30)
@given(num_codes=ANY_K, batch=BATCH, grid=GRID, seed=SEED, scale=st.sampled_from([0.0, 1.0, 10.0]))
def test_gumbel_sampling_is_deterministic_and_never_draws_a_zero_class(num_codes, batch, grid, seed, scale):
    """gumbel_sample with a seeded generator (one, or one per sample) is deterministic, returns codes in
    [0, C), never draws a class at LOG_ZERO (the MASK row of an x_0 prediction; the Gumbel noise spans
    < 21 nats), and returns the code of a one-hot input."""
    length = grid * grid
    log_x0 = soft_log_x0(seed, batch, num_codes, length, scale, mask_mass=False)
    first = D.gumbel_sample(log_x0, gen(seed))
    assert first.shape == (batch, length) and first.dtype == torch.long
    assert torch.equal(first, D.gumbel_sample(log_x0, gen(seed)))
    assert ((first >= 0) & (first < num_codes)).all(), "drew MASK from an x_0 prediction"
    per_sample = [gen(seed + b) for b in range(batch)]
    drawn = D.gumbel_sample(log_x0, per_sample)
    assert torch.equal(drawn, D.gumbel_sample(log_x0, [gen(seed + b) for b in range(batch)]))
    assert torch.equal(drawn[-1:], D.gumbel_sample(log_x0[-1:], [gen(seed + batch - 1)]))
    codes = torch.randint(0, num_codes + 1, (batch, length), generator=gen(seed + 7))
    assert torch.equal(D.gumbel_sample(log_onehot_BCL(codes, num_codes + 1), gen(seed)), codes)


@_settings(30)
@given(num_codes=ANY_K, num_steps=STEPS, ends=end_points(), batch=BATCH, grid=GRID, seed=SEED, data=st.data())
def test_q_sample_is_deterministic_and_stays_in_the_support(num_codes, num_steps, ends, batch, grid, seed, data):
    """q_sample with a seeded generator is deterministic; t = -1 is the identity; x_t is x_0 or MASK
    wherever the reference replace mass K beta_bar_t is 0, never MASK where gamma_bar_t is 0, and always
    MASK where gamma_bar_t is 1."""
    schedule = D.MaskReplaceSchedule(num_codes, num_steps, **ends)
    ref = Reference(num_codes, num_steps, **ends)
    length = grid * grid
    t_list = data.draw(st.lists(step_of(num_steps), min_size=batch, max_size=batch), label="t")
    x0 = torch.randint(0, num_codes, (batch, length), generator=gen(seed))
    x_t = schedule.q_sample(x0, torch.tensor(t_list), gen(seed + 1))
    assert torch.equal(x_t, schedule.q_sample(x0, torch.tensor(t_list), gen(seed + 1)))
    assert ((x_t >= 0) & (x_t <= num_codes)).all()
    assert torch.equal(schedule.q_sample(x0, torch.full((batch,), -1), gen(seed)), x0)
    for b, t in enumerate(t_list):
        _, beta_bar, gamma_bar = ref.cumulative(-1, t)
        if beta_bar == 0.0:
            assert ((x_t[b] == x0[b]) | (x_t[b] == num_codes)).all()
        if gamma_bar == 0.0:
            assert (x_t[b] != num_codes).all()
        if gamma_bar == 1.0:
            assert (x_t[b] == num_codes).all()


@_settings(25)
@given(num_steps=STEPS, ends=end_points())
def test_masked_ce_weights_are_the_unmasking_probability(num_steps, ends):
    """The absorbing-loss weights w_t = (gamma_bar_t - gamma_bar_{t-1}) / gamma_bar_t (0 where
    gamma_bar_t = 0) lie in [0, 1] and match the float64 reference (gamma_bar from the products)."""
    schedule = D.MaskReplaceSchedule(2, num_steps, **ends)
    ref = Reference(2, num_steps, **ends)
    gamma_bar = np.concatenate([[0.0], 1.0 - np.cumprod(1.0 - ref.gamma)])  # index 0: t = -1
    expected = torch.tensor(
        [
            (gamma_bar[t + 1] - gamma_bar[t]) / gamma_bar[t + 1] if gamma_bar[t + 1] > 0 else 0.0
            for t in range(num_steps)
        ],
        dtype=torch.float64,
    )
    weights = schedule.masked_ce_weight_T.double()
    assert torch.isfinite(weights).all() and (weights >= 0).all() and (weights <= 1.0 + 1e-6).all()
    # Where gamma_bar_t is below 1e-9 the ratio is one of float64 rounding noise (and the module snaps
    # probabilities under 1e-14 to exactly 0, weight 0): only the range is checked there.
    defined = torch.from_numpy(gamma_bar[1:] >= 1e-9)
    torch.testing.assert_close(weights[defined], expected[defined], atol=1e-5, rtol=1e-5)


@_settings(25)
@given(
    num_codes=SMALL_K,
    num_steps=SMALL_STEPS,
    ends=end_points(),
    batch=BATCH,
    grid=GRID,
    seed=SEED,
    scale=st.sampled_from([0.0, 1.0, 10.0]),
)
def test_vb_loss_is_finite_nonnegative_and_zero_for_the_truth(num_codes, num_steps, ends, batch, grid, seed, scale):
    """vb_loss: a KL between two posteriors, so L_t >= 0 (up to fp32) and finite for any prediction;
    about 0 for t > 0 when the prediction is the true x_0."""
    schedule = D.MaskReplaceSchedule(num_codes, num_steps, **ends)
    length = grid * grid
    x0 = torch.randint(0, num_codes, (batch, length), generator=gen(seed))
    t_B = torch.randint(0, num_steps, (batch,), generator=gen(seed + 1))
    x_t = schedule.q_sample(x0, t_B, gen(seed + 2))
    pred = soft_log_x0(seed + 3, batch, num_codes, length, scale, mask_mass=False)
    terms = D.vb_loss(pred, x0, x_t, t_B, schedule)
    for value in (terms.loss_B, terms.lt_B, terms.aux_B):
        assert torch.isfinite(value).all()
    assert (terms.lt_B >= -1e-4 * length).all()
    exact = D.vb_loss(log_onehot_BCL(x0, num_codes + 1), x0, x_t, t_B, schedule)
    assert (exact.lt_B[t_B > 0].abs() <= 1e-3 * length).all()


@_settings(30)
@given(a=st.one_of(st.sampled_from([0.0, -1e-30, -1e-12, -math.log(2.0), -69.9, -70.0, -1e4]), st.floats(-100.0, 0.0)))
def test_log1mexp_matches_float64_math(a):
    """log1mexp(a) = log(1 - exp(a)) in float64, floored at LOG_ZERO (a = 0 gives the floor, not -inf)."""
    value = D.log1mexp(torch.tensor([a], dtype=torch.float64)).item()
    # 1 - exp(a) as a float64 expm1 (exact to 1 ulp); log1p of its difference from 1 near 1, log elsewhere.
    one_minus = -math.expm1(a) if a < 0 else 0.0
    expected = -math.inf if one_minus == 0 else math.log1p(math.exp(a) * -1.0) if a < -1.0 else math.log(one_minus)
    expected = max(expected, LOG_ZERO)
    assert abs(value - expected) <= 1e-15 + 1e-12 * abs(expected), (value, expected)

"""Discrete-diffusion maths of a VQ-Diffusion style decoder over a tokenizer's codes.

The mask-and-replace forward process (VQ-Diffusion, docs/diffusion.md, sections 1-3), its posteriors, the
variational and the absorbing-state losses, importance sampling of timesteps, classifier-free
guidance on x0-predictions, truncation and Gumbel sampling.  Registration, the training stage and
the samplers build on these functions; nothing here owns weights.

Conventions
-----------
- K code classes 0..K-1 and MASK = K; a distribution over every token of a sequence is laid out
  (B, C, L): C = K + 1 classes on axis 1, L tokens last (``log_x0_BCL``).
- Steps are t = 0..T-1 and x_t has been noised t + 1 times.  t = -1 stands for "no noise": the
  transition from step -1 is the identity, so q(x_{-1} | x_0) = x_0 and a posterior towards
  s = -1 is the x0 distribution itself (VQ-Diffusion's extra table entry at index T).
- All maths is in log space and at least float32 (bf16/fp16 inputs are promoted first).  There is one
  finite floor, ``LOG_ZERO = -70`` (exp(-70) ~ 4e-31), for "probability zero": nothing takes log(0)
  and no -inf ever reaches a subtraction, so (-inf) - (-inf) = NaN cannot arise.  Public outputs are
  clamped to [LOG_ZERO, 0]; unnormalised intermediates may leave that range but stay finite.
- The schedule is computed in float64 (:mod:`.schedules`) and stored as float32 tables of the
  transition from every step s to every later step t, O(T^2) entries (5 tables of 101 x 101 at
  T = 100).  A skipped-step posterior needs beta_bar_{t|s}, a difference of two nearly equal numbers
  (for the released schedule 1e-6 next to 1); recomputing it from float32 cumulative products would
  be wrong by percents, from the float64 table it is exact to float32 rounding.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from .schedules import schedule_tables

#: log of "probability zero": the single finite floor of all log-space maths in this module.
LOG_ZERO = -70.0

_LN2 = math.log(2.0)
#: exp(LOG_ZERO): probabilities below it are "zero" (their log would fall under the floor).
_PROB_ZERO = math.exp(LOG_ZERO)


# -- log-space helpers --------------------------------------------------------------------------


def log1mexp(a: torch.Tensor | float) -> torch.Tensor:
    """log(1 - exp(a)) for a <= 0, accurate over the whole range and never below ``LOG_ZERO``.

    Near 0, 1 - exp(a) cancels catastrophically, so there it is -expm1(a); far below 0, exp(a) is tiny
    and log1p(-exp(a)) keeps its digits (Maechler 2012: switch at a = -ln 2).  a is clamped to
    <= -exp(LOG_ZERO), so a = 0 gives LOG_ZERO instead of -inf, and gradients stay finite.
    """
    a = torch.as_tensor(a)
    if not a.is_floating_point():
        a = a.double()
    a = a.clamp(max=-_PROB_ZERO)
    near_zero = a > -_LN2
    # Each branch is evaluated on inputs of its own domain only: torch.where would otherwise
    # propagate an inf/NaN gradient from the branch it did not choose.
    a_near = torch.where(near_zero, a, torch.full_like(a, -1.0))
    a_far = torch.where(near_zero, torch.full_like(a, -1.0), a)
    value = torch.where(near_zero, torch.log(-torch.expm1(a_near)), torch.log1p(-torch.exp(a_far)))
    return value.clamp_min(LOG_ZERO)


def log_add_exp(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """log(exp(a) + exp(b)) with the floor: inputs below ``LOG_ZERO`` (-inf included) count as zero
    probability, so the result is finite (>= LOG_ZERO) whenever the inputs are not NaN."""
    return torch.logaddexp(a.clamp_min(LOG_ZERO), b.clamp_min(LOG_ZERO))


def _safe_log(probabilities: torch.Tensor) -> torch.Tensor:
    """log of probabilities with 0 (and anything below exp(LOG_ZERO)) mapped to LOG_ZERO."""
    return torch.log(probabilities.clamp_min(_PROB_ZERO))


def _as_log_probs(log_probs: torch.Tensor) -> torch.Tensor:
    """Promote to at least float32 and clamp into [LOG_ZERO, 0] (-inf inputs become the floor)."""
    dtype = torch.promote_types(log_probs.dtype, torch.float32)
    return log_probs.to(dtype).clamp(LOG_ZERO, 0.0)


def log_onehot(codes_BL: torch.Tensor, num_classes: int) -> torch.Tensor:
    """One-hot distributions (B, num_classes, L) in log space: 0 at the code, ``LOG_ZERO`` elsewhere."""
    codes_BL = codes_BL.long()
    if codes_BL.numel() and (codes_BL.min() < 0 or codes_BL.max() >= num_classes):
        raise ValueError(f"codes must lie in [0, {num_classes}); got [{int(codes_BL.min())}, {int(codes_BL.max())}]")
    out_BCL = torch.full((codes_BL.shape[0], num_classes, codes_BL.shape[1]), LOG_ZERO, device=codes_BL.device)
    return out_BCL.scatter_(1, codes_BL.unsqueeze(1), 0.0)


def log_predict_x0(logits_BKL: torch.Tensor) -> torch.Tensor:
    """The network's x0 distribution: log_softmax over the K code classes (in float32), with a
    ``LOG_ZERO`` MASK row appended (x0 is never MASK), clamped to [LOG_ZERO, 0] -> (B, K+1, L)."""
    log_p_BKL = F.log_softmax(logits_BKL.to(torch.promote_types(logits_BKL.dtype, torch.float32)), dim=1)
    mask_row_B1L = torch.full_like(log_p_BKL[:, :1], LOG_ZERO)
    return torch.cat([log_p_BKL, mask_row_B1L], dim=1).clamp(LOG_ZERO, 0.0)


# -- linear maps of the transition matrix in log space --------------------------------------------
# A transition from step s to step t is the (K+1) x (K+1) matrix Q with, for codes k, j < K,
# Q[k, j] = a 1[j = k] + b,  Q[k, MASK] = g,  Q[MASK, MASK] = 1  (a = alpha_bar_{t|s},
# b = beta_bar_{t|s}, g = gamma_bar_{t|s}, a + K b + g = 1).  Because Q is "a I + b J" on the codes,
# both products below cost O(K) per token instead of O(K^2).  la, lb, lg are their logs, (B, 1, 1).


def _forward_codes(log_u_BKL: torch.Tensor, la: torch.Tensor, lb: torch.Tensor, lg: torch.Tensor) -> torch.Tensor:
    """log(x Q) for an (unnormalised) x with no MASK mass, given as its K code rows -> (B, K+1, L)."""
    code_mass_B1L = torch.logsumexp(log_u_BKL, dim=1, keepdim=True)
    codes_BKL = torch.logaddexp(log_u_BKL + la, lb + code_mass_B1L)
    return torch.cat([codes_BKL, lg + code_mass_B1L], dim=1)


def _forward(log_x_BCL: torch.Tensor, la: torch.Tensor, lb: torch.Tensor, lg: torch.Tensor) -> torch.Tensor:
    """log(x Q): the distribution of the later state when the earlier one is distributed as x (any
    mass on MASK stays on MASK, which is absorbing)."""
    num_codes = log_x_BCL.shape[1] - 1
    out_BCL = _forward_codes(log_x_BCL[:, :num_codes], la, lb, lg)
    mask_B1L = torch.logaddexp(out_BCL[:, num_codes:], log_x_BCL[:, num_codes:])
    return torch.cat([out_BCL[:, :num_codes], mask_B1L], dim=1)


def _likelihood(log_y_BCL: torch.Tensor, la: torch.Tensor, lb: torch.Tensor, lg: torch.Tensor) -> torch.Tensor:
    """log(Q y): entry k is sum_j q(later = j | earlier = k) y_j, i.e. for a one-hot y = x_t the
    likelihood q(x_t | x_s = k) as a function of the earlier state k."""
    num_codes = log_y_BCL.shape[1] - 1
    codes_y_BKL, mask_y_B1L = log_y_BCL[:, :num_codes], log_y_BCL[:, num_codes:]
    code_mass_B1L = torch.logsumexp(codes_y_BKL, dim=1, keepdim=True)
    codes_BKL = torch.logaddexp(torch.logaddexp(codes_y_BKL + la, lb + code_mass_B1L), lg + mask_y_B1L)
    return torch.cat([codes_BKL, mask_y_B1L], dim=1)  # from MASK only MASK is reachable


# -- schedule -----------------------------------------------------------------------------------


class MaskReplaceSchedule(nn.Module):
    """VQ-Diffusion's mask-and-replace forward process over K codes and MASK = K, with T steps.

    alpha_bar_t (probability that x_t is still x_0 by never having moved) falls linearly from ``att_1``
    to ``att_T`` and gamma_bar_t (probability that x_t is MASK) rises linearly from ``ctt_1`` to
    ``ctt_T`` over t = 0..T-1; beta_bar_t = (1 - alpha_bar_t - gamma_bar_t) / K is the probability of
    each code through replacement.  Per step: alpha_t = alpha_bar_t / alpha_bar_{t-1},
    1 - gamma_t = (1 - gamma_bar_t) / (1 - gamma_bar_{t-1}), beta_t = (1 - alpha_t - gamma_t) / K.

    The defaults are the released ones (0.99999, 9e-6, 9e-6, 0.99999): alpha_bar_t + gamma_bar_t =
    0.999999 at every t, so the replace mass K*beta_bar_t is 1e-6 (see :meth:`replace_mass`) and the
    process is, in effect, pure absorbing (masking only).  Real replacement noise needs e.g.
    ``att_T = 0, ctt_T = 0.9`` (replace mass 0.1 at the last step).

    A module only to follow ``.to(device)``: its float32 tables are non-persistent buffers, rebuilt
    from the constructor arguments, so checkpoints do not carry them.  The float64 schedule is kept as
    attributes ``alpha``, ``beta``, ``gamma`` (T,) and ``alpha_bar``, ``beta_bar``, ``gamma_bar``
    (T+1,), index T = step -1 (the identity), for inspection and tests.  Do not cast an owning module
    to half precision with ``.to(dtype)``: that casts these buffers too (the maths itself promotes
    its inputs to float32, but rounded tables stay rounded).
    """

    def __init__(
        self,
        num_codes: int,
        num_steps: int,
        att_1: float = 0.99999,
        att_T: float = 0.000009,
        ctt_1: float = 0.000009,
        ctt_T: float = 0.99999,
    ) -> None:
        super().__init__()
        tables = schedule_tables(num_codes, num_steps, att_1, att_T, ctt_1, ctt_T)
        #: Number of code classes K (MASK is class K).
        self.num_codes = num_codes
        #: Number of classes C = K + 1 of a token's distribution.
        self.num_classes = num_codes + 1
        #: Index of the MASK class.
        self.mask_index = num_codes
        #: Number of steps T (t = 0..T-1).
        self.num_steps = num_steps
        #: The constructor's end points, e.g. for a config or a log line.
        self.end_points = {"att_1": att_1, "att_T": att_T, "ctt_1": ctt_1, "ctt_T": ctt_T}
        for name in ("alpha", "beta", "gamma", "alpha_bar", "beta_bar", "gamma_bar"):
            setattr(self, name, tables[name])
        A, B, G = tables["A"], tables["B"], tables["G"]
        self.register_buffer("log_alpha_TS", _safe_log(A).float(), persistent=False)
        self.register_buffer("log_beta_TS", _safe_log(B).float(), persistent=False)
        self.register_buffer("log_gamma_TS", _safe_log(G).float(), persistent=False)
        # log(alpha + beta): the probability of x_t = x_s for a code, summed in float64 (beta can be
        # 1e-7 next to alpha = 1; a float32 logaddexp would round it away).
        self.register_buffer("log_stay_TS", _safe_log(A + B).float(), persistent=False)
        # Exact probabilities for sampling x_t ~ q(x_t | x_0): a floored log would turn the identity's
        # zero masking probability into exp(-70), which a uniform draw of exactly 0 would hit.
        self.register_buffer("gamma_bar_T1", tables["gamma_bar"].float(), persistent=False)
        self.register_buffer("replace_mass_T1", (num_codes * tables["beta_bar"]).float(), persistent=False)
        self.register_buffer("masked_ce_weight_T", tables["masked_ce_weight"].float(), persistent=False)

    # -- indexing ---------------------------------------------------------------------------------
    def _steps(self, t: torch.Tensor | int, low: int = -1) -> torch.Tensor:
        """t as a long tensor on the schedule's device, checked to lie in [low, T-1]."""
        t = torch.as_tensor(t, device=self.log_alpha_TS.device).long()
        if t.numel() and (t.min() < low or t.max() >= self.num_steps):
            raise ValueError(
                f"timesteps must lie in [{low}, {self.num_steps - 1}]; got [{int(t.min())}, {int(t.max())}]"
            )
        return t

    def _table_index(self, t: torch.Tensor) -> torch.Tensor:
        return torch.where(t < 0, self.num_steps, t)

    def _params(self, t_B: torch.Tensor, s_B: torch.Tensor | int) -> tuple[torch.Tensor, ...]:
        """log alpha_bar, beta_bar, gamma_bar and log(alpha_bar + beta_bar) of the transition s -> t,
        each (B, 1, 1) (s = -1: from x_0)."""
        s_B = torch.as_tensor(s_B, device=t_B.device).long().expand_as(t_B)
        rows, cols = self._table_index(t_B), self._table_index(s_B)
        return tuple(
            table[rows, cols].view(-1, 1, 1)
            for table in (self.log_alpha_TS, self.log_beta_TS, self.log_gamma_TS, self.log_stay_TS)
        )

    def _check_layout(self, log_x_BCL: torch.Tensor, t_B: torch.Tensor) -> None:
        if log_x_BCL.ndim != 3 or log_x_BCL.shape[1] != self.num_classes:
            raise ValueError(f"expected log-probabilities (B, {self.num_classes}, L); got {tuple(log_x_BCL.shape)}")
        if t_B.shape != (log_x_BCL.shape[0],):
            raise ValueError(f"expected one timestep per sample, shape ({log_x_BCL.shape[0]},); got {tuple(t_B.shape)}")

    # -- public API -------------------------------------------------------------------------------
    def replace_mass(self, t: torch.Tensor | int) -> torch.Tensor:
        """K * beta_bar_t: the probability that x_t is a code reached by replacement (x_0 itself
        included) rather than by keeping x_0 or masking; 1e-6 at every t for the released defaults."""
        return self.replace_mass_T1[self._table_index(self._steps(t))]

    def q_pred(self, log_x0_BCL: torch.Tensor, t_B: torch.Tensor) -> torch.Tensor:
        """log q(x_t | x_0) (B, C, L) for x_0 distributed as ``log_x0_BCL`` (one-hot or not); t = -1
        returns x_0 itself."""
        t_B = self._steps(t_B)
        self._check_layout(log_x0_BCL, t_B)
        la, lb, lg, _ = self._params(t_B, -1)
        return _forward(_as_log_probs(log_x0_BCL), la, lb, lg).clamp(LOG_ZERO, 0.0)

    def q_pred_one_step(self, log_x_t_BCL: torch.Tensor, t_B: torch.Tensor) -> torch.Tensor:
        """log q(x_t | x_{t-1} = k) as a function of the earlier state k (B, C, L), for x_t given as a
        (one-hot) distribution ``log_x_t_BCL``: the likelihood factor of the posterior.  The MASK row
        is log 1 where x_t is MASK and ``LOG_ZERO`` elsewhere (MASK never leaves MASK)."""
        t_B = self._steps(t_B, low=0)
        self._check_layout(log_x_t_BCL, t_B)
        la, lb, lg, _ = self._params(t_B, t_B - 1)
        return _likelihood(_as_log_probs(log_x_t_BCL), la, lb, lg).clamp(LOG_ZERO, 0.0)

    def q_sample(
        self, codes_BL: torch.Tensor, t_B: torch.Tensor, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """Draw x_t ~ q(x_t | x_0) for integer codes x_0 (B, L) in [0, K); returns long codes in [0, K].

        One uniform u per token: MASK if u < gamma_bar_t, else a uniformly drawn code if
        u < gamma_bar_t + K beta_bar_t (which may be x_0 itself: that is the beta_bar_t in
        q(x_t = x_0) = alpha_bar_t + beta_bar_t), else x_0.  ``generator`` must live on the codes' device.
        """
        t_B = self._steps(t_B)
        if codes_BL.ndim != 2 or t_B.shape != (codes_BL.shape[0],):
            raise ValueError(
                f"expected codes (B, L) and timesteps (B,); got {tuple(codes_BL.shape)} and {tuple(t_B.shape)}"
            )
        codes_BL = codes_BL.long()
        uniform_BL = torch.rand(codes_BL.shape, generator=generator, device=codes_BL.device, dtype=torch.float32)
        replacement_BL = torch.randint(0, self.num_codes, codes_BL.shape, generator=generator, device=codes_BL.device)
        index = self._table_index(t_B)
        gamma_bar_B1 = self.gamma_bar_T1[index].unsqueeze(1)
        replace_B1 = self.replace_mass_T1[index].unsqueeze(1)
        noised_BL = torch.where(uniform_BL < gamma_bar_B1 + replace_B1, replacement_BL, codes_BL)
        return torch.where(uniform_BL < gamma_bar_B1, torch.full_like(codes_BL, self.mask_index), noised_BL)

    def posterior(
        self, log_x0_BCL: torch.Tensor, codes_t_BL: torch.Tensor, t_B: torch.Tensor, s_B: torch.Tensor | None = None
    ) -> torch.Tensor:
        """log p(x_s | x_t) (B, C, L), normalised over classes and clamped to [LOG_ZERO, 0].

        For a one-hot x_0 this is q(x_s | x_t, x_0) = q(x_t | x_s) q(x_s | x_0) / q(x_t | x_0).  For a
        predicted distribution p(x_0) it is sum_k q(x_s | x_t, x_0 = k) p(k), computed without the sum
        over k (docs/diffusion.md section 2, generalised to a skip s < t - 1):

          1. a_k = log q(x_t | x_0 = k)            for each code k (x_0 is never MASK; its MASK row is
                                                   ignored);
          2. u_k = log p(k) - a_k, normalised by its logsumexp Z (which only keeps the numbers in range);
          3. v = log(u Q_{0->s}): the weights pushed to step s through q(x_s | x_0), O(K);
          4. log p(x_s) = v + log q(x_t | x_s), with q(x_t | x_s) the multi-step transition s -> t
             (alpha_bar_t / alpha_bar_s, (1 - gamma_bar_t) / (1 - gamma_bar_s)), then normalised.

        ``s_B`` defaults to t - 1; any -1 <= s < t is allowed (a strided sampler's jump), and s = -1
        returns the x_0 distribution itself.

        A prediction p(k) > 0 for a code k other than an unmasked x_t = j is taken at its word (as in
        VQ-Diffusion): x_t = j is then explained as a replacement, and x_s = k gets a weight of about
        p(k) beta_bar_{t|s} / beta_bar_t, which is not small even for the released 1e-6 replace mass.
        With exactly zero replace noise both beta_bars are the floor exp(-70), their ratio is 1, and
        unmasked tokens can then change with probability ~p(k): a sampler for a pure-mask schedule
        should keep unmasked tokens fixed (or feed p(x_0) = onehot(x_t) at those positions).
        """
        t_B = self._steps(t_B, low=0)
        self._check_layout(log_x0_BCL, t_B)
        s_B = t_B - 1 if s_B is None else torch.as_tensor(s_B, device=t_B.device).long().expand_as(t_B)
        if s_B.numel() and ((s_B < -1) | (s_B >= t_B)).any():
            raise ValueError("posterior needs -1 <= s < t for every sample")
        if codes_t_BL.shape != (log_x0_BCL.shape[0], log_x0_BCL.shape[2]):
            raise ValueError(
                f"codes_t must be (B, L) = {(log_x0_BCL.shape[0], log_x0_BCL.shape[2])}; got {tuple(codes_t_BL.shape)}"
            )
        num_codes = self.num_codes
        log_x0_BKL = _as_log_probs(log_x0_BCL)[:, :num_codes]
        codes_t_BL = codes_t_BL.long()
        is_mask_B1L = (codes_t_BL == num_codes).unsqueeze(1)
        is_code_BKL = codes_t_BL.unsqueeze(1) == torch.arange(num_codes, device=codes_t_BL.device).view(1, -1, 1)

        # 1. log q(x_t | x_0 = k), read directly off the code of x_t (exact, no one-hot floor mixed in).
        _, lb_t, lg_t, lstay_t = self._params(t_B, -1)
        log_qt_x0_BKL = torch.where(is_mask_B1L, lg_t, torch.where(is_code_BKL, lstay_t, lb_t))
        # 2. weights p(k) / q(x_t | k), normalised for range only (the final normalisation fixes scale).
        log_u_BKL = log_x0_BKL - log_qt_x0_BKL
        log_u_BKL = log_u_BKL - torch.logsumexp(log_u_BKL, dim=1, keepdim=True)
        # 3. through q(x_s | x_0).
        la_s, lb_s, lg_s, _ = self._params(s_B, -1)
        log_xs_BCL = _forward_codes(log_u_BKL, la_s, lb_s, lg_s)
        # 4. times the likelihood q(x_t | x_s) of the jump s -> t.
        _, lb_ts, lg_ts, lstay_ts = self._params(t_B, s_B)
        likelihood_codes_BKL = torch.where(is_mask_B1L, lg_ts, torch.where(is_code_BKL, lstay_ts, lb_ts))
        likelihood_mask_B1L = torch.where(is_mask_B1L, 0.0, LOG_ZERO).to(likelihood_codes_BKL.dtype)
        log_post_BCL = log_xs_BCL + torch.cat([likelihood_codes_BKL, likelihood_mask_B1L], dim=1)
        log_post_BCL = log_post_BCL - torch.logsumexp(log_post_BCL, dim=1, keepdim=True)
        return log_post_BCL.clamp(LOG_ZERO, 0.0)


# -- losses ---------------------------------------------------------------------------------------


def _categorical_kl(log_p_BCL: torch.Tensor, log_q_BCL: torch.Tensor) -> torch.Tensor:
    """sum over classes and tokens of p (log p - log q), per sample (B,)."""
    return (log_p_BCL.exp() * (log_p_BCL - log_q_BCL)).sum(dim=(1, 2))


@dataclass
class VBLoss:
    """The terms of :func:`vb_loss`, all per sample (B,) and summed over tokens."""

    #: What to optimise: (lt_B + aux_weight * ((1 - t/T) + 1) * aux_B) / p_t_B.  Divide its sum by
    #: B * L for VQ-Diffusion's normalisation.
    loss_B: torch.Tensor
    #: L_t: KL(q(x_{t-1} | x_t, x_0) || p(x_{t-1} | x_t)) for t > 0, decoder NLL -log p(x_0 | x_t) for
    #: t = 0.  Feed it to :meth:`TimestepSampler.update`.
    lt_B: torch.Tensor
    #: The auxiliary term: KL(onehot(x_0) || p(x_0 | x_t)) over the K codes for t > 0, the decoder
    #: NLL for t = 0 (as VQ-Diffusion).
    aux_B: torch.Tensor


def vb_loss(
    log_x0_pred_BCL: torch.Tensor,
    codes_x0_BL: torch.Tensor,
    codes_t_BL: torch.Tensor,
    t_B: torch.Tensor,
    schedule: MaskReplaceSchedule,
    aux_weight: float = 1e-3,
    p_t_B: torch.Tensor | None = None,
) -> VBLoss:
    """VQ-Diffusion's training loss (docs/diffusion.md section 3) for x_t ~ q(x_t | x_0) at steps ``t_B``.

    ``log_x0_pred_BCL`` is the network's x_0 distribution (:func:`log_predict_x0`); ``p_t_B`` the
    probability with which each t was drawn (:meth:`TimestepSampler.sample`; None = 1).  The aux
    weight is 5e-4 for text and 1e-3 for ImageNet in VQ-Diffusion.  No masked/unmasked token weights:
    every token counts once.
    """
    t_B = torch.as_tensor(t_B, device=log_x0_pred_BCL.device).long()
    log_pred_BCL = _as_log_probs(log_x0_pred_BCL)
    log_true_x0_BCL = log_onehot(codes_x0_BL, schedule.num_classes)
    log_true_BCL = schedule.posterior(log_true_x0_BCL, codes_t_BL, t_B)
    log_model_BCL = schedule.posterior(log_pred_BCL, codes_t_BL, t_B)
    kl_B = _categorical_kl(log_true_BCL, log_model_BCL)
    decoder_nll_B = -log_model_BCL.gather(1, codes_x0_BL.long().unsqueeze(1)).sum(dim=(1, 2))
    is_first_B = t_B == 0
    lt_B = torch.where(is_first_B, decoder_nll_B, kl_B)
    num_codes = schedule.num_codes
    aux_kl_B = _categorical_kl(log_true_x0_BCL[:, :num_codes], log_pred_BCL[:, :num_codes])
    aux_B = torch.where(is_first_B, decoder_nll_B, aux_kl_B)
    # Emphasise the x_0 prediction more at small t (VQ-Diffusion's adaptive auxiliary weight).
    aux_scale_B = (1.0 - t_B.to(lt_B.dtype) / schedule.num_steps) + 1.0
    loss_B = lt_B + aux_weight * aux_scale_B * aux_B
    if p_t_B is not None:
        loss_B = loss_B / p_t_B.to(loss_B)
    return VBLoss(loss_B, lt_B, aux_B)


def masked_ce_loss(
    logits_BKL: torch.Tensor,
    codes_x0_BL: torch.Tensor,
    codes_t_BL: torch.Tensor,
    t_B: torch.Tensor,
    schedule: MaskReplaceSchedule,
    weighting: str = "elbo",
) -> torch.Tensor:
    """The absorbing-state loss L_t (MD4/MDLM, docs/diffusion.md section 3), per sample (B,): w_t times the summed
    cross-entropy -log p(x_0 | x_t) of the masked tokens only; unmasked tokens contribute nothing.

    Weight: w_t = (gamma_bar_t - gamma_bar_{t-1}) / gamma_bar_t with gamma_bar_{-1} = 0 (so w_0 = 1).
    Why: for a token masked at t, q(x_{t-1} | x_t = MASK, x_0) puts exactly this mass on x_0 (the
    chance it was unmasked one step earlier) and the rest on MASK, and so does the model posterior
    with p(x_0) in place of onehot(x_0); their KL is therefore w_t * (-log p(x_0 | x_t)), and for an
    unmasked token it is 0.  So this is exactly the step-t KL term of the discrete-time ELBO of the
    absorbing process (the same scale as :attr:`VBLoss.lt_B`), and as T -> infinity it becomes
    MD4/MDLM's continuous weight alpha'_t / (1 - alpha_t).  For the linear gamma_bar of the released
    schedule w_t ~ 1/t.  Divide by p_t as for the VB loss (uniform t: multiply by T for the ELBO).
    With real replace noise this ignores replaced tokens: it is then the absorbing approximation,
    and :func:`vb_loss` is the exact objective.  A step with gamma_bar_t = 0 has no masked tokens and
    weight 0.

    ``weighting="mean"`` instead gives each sample the mean cross-entropy of its masked tokens
    (MaskGIT's objective, not a bound): every masked token counts alike whatever t, where the
    ELBO weight w_t ~ 1/t makes a token masked at large t (where the condition decides the
    layout) count ~T times less than one masked at t = 0.
    """
    if weighting not in ("elbo", "mean"):
        raise ValueError(f"masked_ce_loss weighting must be 'elbo' or 'mean'; got {weighting!r}")
    num_codes = schedule.num_codes
    if logits_BKL.ndim != 3 or logits_BKL.shape[1] != num_codes:
        raise ValueError(f"expected logits (B, {num_codes}, L); got {tuple(logits_BKL.shape)}")
    t_B = schedule._steps(t_B, low=0)
    log_p_BKL = F.log_softmax(logits_BKL.to(torch.promote_types(logits_BKL.dtype, torch.float32)), dim=1)
    nll_BL = -log_p_BKL.gather(1, codes_x0_BL.long().unsqueeze(1)).squeeze(1)
    # where, not a product: a -inf logit at an unmasked position must not turn 0 * inf into NaN.
    is_masked_BL = codes_t_BL == schedule.mask_index
    masked_nll_BL = torch.where(is_masked_BL, nll_BL, torch.zeros_like(nll_BL))
    if weighting == "mean":
        return masked_nll_BL.sum(dim=1) / is_masked_BL.sum(dim=1).clamp_min(1).to(nll_BL.dtype)
    return schedule.masked_ce_weight_T[t_B].to(nll_BL.dtype) * masked_nll_BL.sum(dim=1)


class TimestepSampler(nn.Module):
    """Importance sampling of training timesteps (VQ-Diffusion, docs/diffusion.md section 3).

    Uniform until every t has been seen more than ``min_count`` times, then p_t proportional to
    sqrt(E[L_t^2]) + ``floor`` with E[L_t^2] an exponential moving average (decay ``decay``) of the
    squared per-sample L_t.  Divide the loss by the returned p_t to keep it unbiased.

    The history and counts are persistent buffers, so a checkpoint of the owning module restores the
    sampler exactly.  They are per process: under data parallelism each rank keeps its own (all-reduce
    them yourself if the ranks must agree).  Samples with the same t in one :meth:`update` are averaged
    first and enter the EMA once (deterministic, unlike a scatter where the last write wins).
    """

    loss_sq_T: torch.Tensor
    count_T: torch.Tensor

    def __init__(self, num_steps: int, min_count: int = 10, decay: float = 0.9, floor: float = 1e-4) -> None:
        super().__init__()
        if num_steps < 1:
            raise ValueError(f"num_steps must be >= 1; got {num_steps}")
        #: Number of steps T.
        self.num_steps = num_steps
        #: Every t must be seen more than this many times before importance sampling starts.
        self.min_count = min_count
        #: EMA decay of the squared losses (new = decay * old + (1 - decay) * L_t^2).
        self.decay = decay
        #: Added to sqrt(E[L_t^2]) so no step's probability falls to zero.
        self.floor = floor
        self.register_buffer("loss_sq_T", torch.zeros(num_steps, dtype=torch.float32))
        self.register_buffer("count_T", torch.zeros(num_steps, dtype=torch.long))

    @property
    def ready(self) -> bool:
        """True once every step has been seen more than ``min_count`` times (importance phase)."""
        return bool((self.count_T > self.min_count).all())

    def probabilities(self) -> torch.Tensor:
        """The current sampling distribution over t (T,), float32."""
        if not self.ready:
            return torch.full((self.num_steps,), 1.0 / self.num_steps, device=self.count_T.device)
        weights_T = self.loss_sq_T.float().clamp_min(0.0).sqrt() + self.floor
        return weights_T / weights_T.sum()

    def sample(self, batch: int, generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Draw ``batch`` timesteps; returns (t_B long, p_t_B float32) on the sampler's device (where
        ``generator`` must live)."""
        device = self.count_T.device
        if not self.ready:
            t_B = torch.randint(0, self.num_steps, (batch,), generator=generator, device=device)
            return t_B, torch.full((batch,), 1.0 / self.num_steps, device=device)
        probabilities_T = self.probabilities()
        t_B = torch.multinomial(probabilities_T, batch, replacement=True, generator=generator)
        return t_B, probabilities_T[t_B]

    @torch.no_grad()
    def update(self, t_B: torch.Tensor, loss_B: torch.Tensor) -> None:
        """Add per-sample losses L_t (e.g. :attr:`VBLoss.lt_B`); non-finite ones are ignored."""
        device = self.count_T.device
        t_B = torch.as_tensor(t_B, device=device).long()
        loss_B = loss_B.detach().to(device=device, dtype=torch.float32)
        finite_B = torch.isfinite(loss_B)
        t_B, loss_sq_B = t_B[finite_B], loss_B[finite_B].square()
        sums_T = torch.zeros(self.num_steps, device=device).index_add_(0, t_B, loss_sq_B)
        counts_T = torch.zeros(self.num_steps, dtype=torch.long, device=device).index_add_(0, t_B, torch.ones_like(t_B))
        mean_T = sums_T / counts_T.clamp_min(1)
        updated_T = self.decay * self.loss_sq_T + (1.0 - self.decay) * mean_T
        self.loss_sq_T.copy_(torch.where(counts_T > 0, updated_T, self.loss_sq_T))
        self.count_T += counts_T


# -- sampling helpers -----------------------------------------------------------------------------


def guided_log_x0(
    log_p_cond_BCL: torch.Tensor, log_p_null_BCL: torch.Tensor, scale: float | torch.Tensor
) -> torch.Tensor:
    """Classifier-free guidance on x_0 predictions: log p_null + s (log p_cond - log p_null) over the
    K codes, renormalised, MASK row ``LOG_ZERO``, clamped to [LOG_ZERO, 0] -> (B, K+1, L) float32.

    Written as (1 - s) log p_null + s log p_cond, so s = 0 and s = 1 return the null and the
    conditional distributions exactly (up to renormalisation rounding).  Inputs are promoted to
    float32 and clamped to [LOG_ZERO, 0] first, so -inf or bf16 inputs and large s (1e4) stay finite.
    ``scale`` may be a float or a per-sample tensor (B,).
    """
    if log_p_cond_BCL.shape != log_p_null_BCL.shape:
        raise ValueError(
            f"conditional and null predictions differ in shape: {tuple(log_p_cond_BCL.shape)} vs "
            f"{tuple(log_p_null_BCL.shape)}"
        )
    num_codes = log_p_cond_BCL.shape[1] - 1
    cond_BKL = _as_log_probs(log_p_cond_BCL)[:, :num_codes]
    null_BKL = _as_log_probs(log_p_null_BCL)[:, :num_codes]
    scale = torch.as_tensor(scale, dtype=cond_BKL.dtype, device=cond_BKL.device)
    if scale.ndim == 1:
        scale = scale.view(-1, 1, 1)
    guided_BKL = (1.0 - scale) * null_BKL + scale * cond_BKL
    # Subtract the maximum first: at s = 1e4 the values reach 1e6, where float32 spacing is 0.06, and
    # x - logsumexp(x) would round the leading entries; x - max is exact for them (Sterbenz).
    guided_BKL = guided_BKL - guided_BKL.amax(dim=1, keepdim=True)
    guided_BKL = (guided_BKL - torch.logsumexp(guided_BKL, dim=1, keepdim=True)).clamp(LOG_ZERO, 0.0)
    return torch.cat([guided_BKL, torch.full_like(guided_BKL[:, :1], LOG_ZERO)], dim=1)


def truncate(log_x0_BCL: torch.Tensor, r: float) -> torch.Tensor:
    """VQ-Diffusion's truncation ``top{r}r`` of an x_0 distribution (B, K+1, L), token by token.

    Codes sorted by probability are kept while the mass of the codes before them is < r (so the code
    that crosses r is kept, and the top-1 always is); the rest get ``LOG_ZERO`` and the kept ones are
    renormalised; the MASK row becomes ``LOG_ZERO``.  r >= 1 is the identity (input promoted to float32
    and clamped), whatever float rounding does to the cumulative sum.
    """
    if not r >= 0.0:
        raise ValueError(f"truncation rate r must be >= 0; got {r}")
    log_x0_BCL = _as_log_probs(log_x0_BCL)
    if r >= 1.0:
        return log_x0_BCL
    num_codes = log_x0_BCL.shape[1] - 1
    log_p_BKL = log_x0_BCL[:, :num_codes]
    sorted_BKL, order_BKL = torch.sort(log_p_BKL, dim=1, descending=True, stable=True)
    mass_BKL = sorted_BKL.exp()
    mass_before_BKL = torch.cat([torch.zeros_like(mass_BKL[:, :1]), mass_BKL.cumsum(dim=1)[:, :-1]], dim=1)
    keep_sorted_BKL = mass_before_BKL < r
    keep_sorted_BKL[:, 0] = True
    keep_BKL = torch.zeros_like(keep_sorted_BKL).scatter(1, order_BKL, keep_sorted_BKL)
    # -inf only inside this logsumexp, which always sees the kept top-1, so it is finite.
    kept_mass_B1L = torch.logsumexp(log_p_BKL.masked_fill(~keep_BKL, float("-inf")), dim=1, keepdim=True)
    truncated_BKL = torch.where(keep_BKL, log_p_BKL - kept_mass_B1L, LOG_ZERO).clamp(LOG_ZERO, 0.0)
    return torch.cat([truncated_BKL, torch.full_like(truncated_BKL[:, :1], LOG_ZERO)], dim=1)


def gumbel_sample(
    log_probs_BCL: torch.Tensor, generator: torch.Generator | Sequence[torch.Generator] | None = None
) -> torch.Tensor:
    """Sample one class per token (B, L) long: argmax over axis 1 of log p + Gumbel noise, with the
    noise -log(-log(u + 1e-30) + 1e-30), u ~ U[0, 1) in float32 (the guards keep u = 0 finite).

    ``generator``: None (global RNG), one ``torch.Generator`` for the whole batch, or a sequence of B
    generators, one per sample.  For a given generator state the result is deterministic.  With one
    generator the noise of row b depends on b's place in the batch, and on CUDA also on the batch's
    size, so a sample's codes change with the batch it is in.  For batch-size-invariant sampling pass
    one generator per sample (e.g. seeded from the sample's id) and advance it identically in every
    call: each row's noise (C, L) is then drawn from its own generator only.  Generators must live on
    the device of ``log_probs_BCL``.
    """
    log_probs_BCL = log_probs_BCL.to(torch.promote_types(log_probs_BCL.dtype, torch.float32))
    if generator is None or isinstance(generator, torch.Generator):
        uniform_BCL = torch.rand(
            log_probs_BCL.shape, generator=generator, device=log_probs_BCL.device, dtype=torch.float32
        )
    else:
        generators = list(generator)
        if len(generators) != log_probs_BCL.shape[0]:
            raise ValueError(f"got {len(generators)} generators for a batch of {log_probs_BCL.shape[0]}")
        uniform_BCL = torch.stack(
            [
                torch.rand(
                    log_probs_BCL.shape[1:], generator=row_generator, device=log_probs_BCL.device, dtype=torch.float32
                )
                for row_generator in generators
            ]
        )
    gumbel_BCL = -torch.log(-torch.log(uniform_BCL + 1e-30) + 1e-30)
    return (log_probs_BCL + gumbel_BCL).argmax(dim=1)

"""The float64 tables of VQ-Diffusion's mask-and-replace schedule (docs/diffusion.md, section 1),
validated: what :class:`.diffusion.MaskReplaceSchedule` stores as float32 buffers.

The transition from every step s to every later step t is tabulated, O(T^2) entries (5 tables of
101 x 101 at T = 100): a skipped-step posterior needs beta_bar_{t|s}, a difference of two nearly
equal numbers (for the released schedule 1e-6 next to 1); recomputing it from float32 cumulative
products would be wrong by percents, from the float64 table it is exact to float32 rounding.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

#: Absolute tolerance of the schedule's probability checks (float64 rounding of sums of order 1).
_SCHEDULE_TOLERANCE = 1e-9
#: Schedule probabilities smaller than this are float64 rounding of differences of numbers of order 1
#: (~1e-16) and are set to exactly 0; real replace probabilities are many orders larger (1e-10 per code
#: per step for the released schedule at T = 1000).
_ROUNDING_ZERO = 1e-14


def schedule_tables(
    num_codes: int, num_steps: int, att_1: float, att_T: float, ctt_1: float, ctt_T: float
) -> dict[str, torch.Tensor]:
    """The float64 mask-and-replace schedule, validated; raises a one-line ValueError when invalid.

    Returns per-step ``alpha``, ``beta``, ``gamma`` (T,), cumulative ``alpha_bar``, ``beta_bar``,
    ``gamma_bar`` (T+1,) with the identity at index T (= step -1), the transition from step s to
    step t as tables ``A``, ``B``, ``G`` (T+1, T+1) indexed [t, s] (s = T means from x_0), and the
    per-step weight ``masked_ce_weight`` (T,) of :func:`.diffusion.masked_ce_loss`.
    """
    refuse = _refusal(num_codes, num_steps, att_1, att_T, ctt_1, ctt_T)
    _check_end_points(refuse, num_codes, num_steps, att_1, att_T, ctt_1, ctt_T)
    forward, A, B, G = _transition_tables(num_codes, num_steps, att_1, att_T, ctt_1, ctt_T)
    per_step = torch.arange(num_steps)
    previous = torch.where(per_step == 0, num_steps, per_step - 1)
    _check_transitions(refuse, forward, A, B, G, per_step, previous)
    # Below _ROUNDING_ZERO a probability is float64 rounding (e.g. 1 - 0.95 - 0.05 = 4e-17), not noise the
    # schedule asked for: snap it to an exact zero, which the log tables then store as LOG_ZERO.
    A, G, B = (torch.where(table.abs() < _ROUNDING_ZERO, 0.0, table) for table in (A, G, B))
    A, G, B = A.clamp(0.0, 1.0), G.clamp(0.0, 1.0), B.clamp_min(0.0)
    total = A + num_codes * B + G
    if (total - 1.0).abs().max() > 1e-6:
        raise refuse("alpha_bar + K beta_bar + gamma_bar != 1")
    return {
        "alpha": A[per_step, previous],
        "beta": B[per_step, previous],
        "gamma": G[per_step, previous],
        "alpha_bar": A[:, num_steps],
        "beta_bar": B[:, num_steps],
        "gamma_bar": G[:, num_steps],
        "A": A,
        "B": B,
        "G": G,
        "masked_ce_weight": _masked_ce_weight(G[:, num_steps], num_steps),
    }


def _refusal(
    num_codes: int, num_steps: int, att_1: float, att_T: float, ctt_1: float, ctt_T: float
) -> Callable[[str], ValueError]:
    """The maker of the one-line ValueError that names the refused schedule and the reason."""
    ends = f"att_1={att_1}, att_T={att_T}, ctt_1={ctt_1}, ctt_T={ctt_T}"

    def refuse(reason: str) -> ValueError:
        return ValueError(f"invalid mask-and-replace schedule ({ends}, K={num_codes}, T={num_steps}): {reason}")

    return refuse


def _check_end_points(
    refuse: Callable[[str], ValueError],
    num_codes: int,
    num_steps: int,
    att_1: float,
    att_T: float,
    ctt_1: float,
    ctt_T: float,
) -> None:
    """Refuse sizes and end points no mask-and-replace schedule can have."""
    if num_codes < 1:
        raise refuse("num_codes must be >= 1")
    if num_steps < 2:
        raise refuse("num_steps must be >= 2 (the end points are the values at t = 0 and t = T-1)")
    for name, value in (("att_1", att_1), ("att_T", att_T), ("ctt_1", ctt_1), ("ctt_T", ctt_T)):
        if not 0.0 <= value <= 1.0:  # also catches NaN
            raise refuse(f"{name} must lie in [0, 1]")
    if att_1 <= 0.0:
        raise refuse("att_1 must be > 0 (alpha_t = alpha_bar_t / alpha_bar_{t-1} is undefined otherwise)")
    if ctt_1 >= 1.0:
        raise refuse("ctt_1 must be < 1 (everything would be masked before the first step)")
    if att_T > att_1:
        raise refuse("att_T > att_1, but alpha_bar (the probability of keeping x_0) cannot increase")
    if ctt_T < ctt_1:
        raise refuse("ctt_T < ctt_1, but gamma_bar (the probability of MASK, which is absorbing) cannot decrease")
    for suffix, alpha_end, gamma_end in (("1", att_1, ctt_1), ("T", att_T, ctt_T)):
        if alpha_end + gamma_end > 1.0 + _SCHEDULE_TOLERANCE:
            raise refuse(
                f"att_{suffix} + ctt_{suffix} = {alpha_end + gamma_end:.9g} > 1 "
                f"(the replace mass K*beta_bar = 1 - att - ctt would be negative)"
            )


def _transition_tables(
    num_codes: int, num_steps: int, att_1: float, att_T: float, ctt_1: float, ctt_T: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Which [t, s] pairs are forward transitions, and the unchecked float64 tables A, B, G of them."""
    f64 = torch.float64
    fraction_T = torch.arange(num_steps, dtype=f64) / (num_steps - 1)
    one = torch.ones(1, dtype=f64)
    alpha_bar = torch.cat([att_1 + fraction_T * (att_T - att_1), one])  # index T: identity
    # keep_bar = 1 - gamma_bar, gamma_bar being the cumulative mask mass from ctt_1 to ctt_T (so > 0 except at
    # the end), interpolated directly from 1 - ctt_1 and 1 - ctt_T: computing 1 - gamma_bar with ctt_1 near 1
    # would cancel and make a pure-mask schedule's beta_t slightly negative (refused) at late steps.
    keep_bar = torch.cat([(1.0 - ctt_1) * (1.0 - fraction_T) + fraction_T * (1.0 - ctt_T), one])

    # Transition from step s (column) to step t (row).  Only s < t (or s = -1, column T) is a forward
    # transition; every other pair is set to the identity so indexing it is harmless.
    index = torch.arange(num_steps + 1)
    t_rows, s_cols = index.view(-1, 1), index.view(1, -1)
    forward = (t_rows < num_steps) & ((s_cols == num_steps) | (s_cols < t_rows))
    # Denominators are > 0 on every forward pair: a source s < t <= T-1 is never the last step, and only
    # the last step can have alpha_bar = 0 or gamma_bar = 1.
    A = torch.where(forward, alpha_bar.view(-1, 1) / alpha_bar.view(1, -1).clamp_min(1e-300), 1.0)
    keep = torch.where(forward, keep_bar.view(-1, 1) / keep_bar.view(1, -1).clamp_min(1e-300), 1.0)
    G = 1.0 - keep
    B = (keep - A) / num_codes
    return forward, A, B, G


def _check_transitions(
    refuse: Callable[[str], ValueError],
    forward: torch.Tensor,
    A: torch.Tensor,
    B: torch.Tensor,
    G: torch.Tensor,
    per_step: torch.Tensor,
    previous: torch.Tensor,
) -> None:
    """Refuse transition probabilities outside [0, 1], beyond float64 rounding."""
    for name, table in (("alpha", A), ("gamma", G)):
        bad = (table[forward] < -_SCHEDULE_TOLERANCE) | (table[forward] > 1.0 + _SCHEDULE_TOLERANCE)
        if bad.any():
            raise refuse(f"a transition probability {name} leaves [0, 1]")
    bad_beta = B[per_step, previous] < -_SCHEDULE_TOLERANCE
    if bad_beta.any():
        step = int(per_step[bad_beta][0])
        raise refuse(
            f"the per-step replace probability beta_t is negative from t = {step}: alpha_bar falls "
            f"too slowly for how fast gamma_bar rises (a token kept with probability alpha_t cannot "
            f"also be masked with probability gamma_t)"
        )
    if (B[forward] < -_SCHEDULE_TOLERANCE).any():
        raise refuse("a multi-step replace probability beta_bar_{t|s} is negative")


def _masked_ce_weight(gamma_bar_T1: torch.Tensor, num_steps: int) -> torch.Tensor:
    """w_t = (gamma_bar_t - gamma_bar_{t-1}) / gamma_bar_t with gamma_bar_{-1} = 0, in [0, 1] (T,)."""
    gamma_bar, gamma_bar_prev = (
        gamma_bar_T1[:num_steps],
        torch.cat([torch.zeros(1, dtype=gamma_bar_T1.dtype), gamma_bar_T1[: num_steps - 1]]),
    )
    # clamp: where gamma_bar barely moves, float64 rounding can make the difference a hair negative.
    return torch.where(gamma_bar > 0, (gamma_bar - gamma_bar_prev) / gamma_bar.clamp_min(1e-300), 0.0).clamp(0, 1)

"""Samplers of the discrete-diffusion generator: how x0 predictions become a grid of codes.

Three strategies, one plugin each (registered in :mod:`.samplers_plugin`, with their options):

- ``posterior``: VQ-Diffusion's reverse chain x_T -> ... -> x_0 (docs/diffusion.md section 4), with ``steps`` timesteps
  evenly spaced from T-1 down to 0 and each jump t -> s computed exactly across the skip
  (:meth:`MaskReplaceSchedule.posterior` with s < t - 1), never "the last ``steps`` steps" (the diffusers
  pitfall, docs/diffusion.md section 4).
- ``purity``: Improved VQ-Diffusion's high-quality inference: each round reveals a fixed number of masked
  tokens, chosen by purity (the largest probability of p(x0 | x_t) at the position).
- ``confidence``: MaskGIT decoding (docs/diffusion.md section 4): sample every masked token, re-mask the least confident
  ones following a cosine schedule.

A sampler sees only ``denoise(codes_t_BL, t_B) -> log p(x0 | x_t)`` (B, K+1, L), already guided and
truncated by the generator, and the schedule (see :class:`vqtouch.core.Sampler`).  Every random draw of
row b comes from ``generators[b]`` alone and every row makes the same draws in the same order whatever
batch it is in, so a row's codes depend only on its own generator's seed (batch-size invariance).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence
from typing import Any

import torch

from vqtouch.core import BuildContext, Sampler, VqtouchWarning
from vqtouch.plugins.generator.diffusion import gumbel_sample

from .samplers_plugin import ConfidenceSamplerConfig, PosteriorSamplerConfig, PuritySamplerConfig

#: ``denoise(codes_t_BL, t_B) -> log p(x0 | x_t)`` (B, K+1, L) float32.
Denoise = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


# -- shared helpers ---------------------------------------------------------------------------------


def check_steps(steps: Any, num_steps: int) -> int:
    """``steps`` as an int, or a one-line ValueError naming the allowed range [1, T]."""
    if isinstance(steps, bool) or not isinstance(steps, int) or not 1 <= steps <= num_steps:
        raise ValueError(
            f"steps must be an integer in [1, {num_steps}] (the schedule's T = {num_steps} diffusion "
            f"steps); got {steps!r}"
        )
    return steps


def _check_call(schedule: Any, length: Any, steps: Any, generators: Sequence[torch.Generator]) -> torch.device:
    """Validate the arguments every sampler takes; returns the device the codes live on (the generators')."""
    check_steps(steps, schedule.num_steps)
    if isinstance(length, bool) or not isinstance(length, int) or length < 1:
        raise ValueError(f"length (tokens per sample) must be an integer >= 1; got {length!r}")
    if len(generators) == 0 or not all(isinstance(g, torch.Generator) for g in generators):
        raise ValueError("generators must be a non-empty list of torch.Generator, one per row")
    # Draws are made on the generators' device (gumbel_sample requires it), so the codes live there too.
    return generators[0].device


def _all_mask(schedule: Any, length: Any, steps: Any, generators: Sequence[torch.Generator]) -> torch.Tensor:
    """The starting point of every sampler, after checking its arguments: (B, length) MASK codes on
    the generators' device."""
    device = _check_call(schedule, length, steps, generators)
    return torch.full((len(generators), length), schedule.mask_index, dtype=torch.long, device=device)


def _draw_masked(
    denoise: Denoise,
    schedule: Any,
    codes_BL: torch.Tensor,
    masked_B: torch.Tensor,
    generators: Sequence[torch.Generator],
) -> tuple[torch.Tensor, torch.Tensor]:
    """One step of the revealing samplers: denoise at the timestep matching each row's masked fraction
    and draw a code for every position; returns log p(x0 | x_t) (B, K+1, L) and the draws (B, L)."""
    t_B = timesteps_for_mask_ratio(schedule, masked_B / codes_BL.shape[1])
    log_x0_BCL = _denoise(denoise, codes_BL, t_B, schedule.num_codes + 1)
    drawn_BL = gumbel_sample(_without_mask(log_x0_BCL, schedule.mask_index), generator=generators)
    return log_x0_BCL, drawn_BL


def _denoise(denoise: Denoise, codes_BL: torch.Tensor, t_B: torch.Tensor, num_classes: int) -> torch.Tensor:
    """Call ``denoise`` and check its layout; returns float32 log p(x0 | x_t) (B, K+1, L)."""
    log_x0_BCL = denoise(codes_BL, t_B)
    expected = (codes_BL.shape[0], num_classes, codes_BL.shape[1])
    if tuple(log_x0_BCL.shape) != expected:
        raise ValueError(f"denoise returned shape {tuple(log_x0_BCL.shape)}; expected (B, K+1, L) = {expected}")
    return log_x0_BCL.float()


def _without_mask(log_probs_BCL: torch.Tensor, mask_index: int) -> torch.Tensor:
    """The distribution with its MASK row at -inf, so a Gumbel draw from it is always a code.

    The inputs' MASK row is already the floor (-70), which Gumbel noise (at most ~17) could not lift over a
    code's log-probability (>= log(1/K) - 4 for the best code); -inf makes "never MASK" a guarantee rather
    than a margin, even for a denoiser that breaks the contract and puts mass on MASK.  The row is kept (not
    sliced off) so each row draws the same (K+1, L) uniforms in every call.
    """
    return log_probs_BCL.index_fill(1, torch.tensor([mask_index], device=log_probs_BCL.device), float("-inf"))


def _row_gumbel(generators: Sequence[torch.Generator], length: int, device: torch.device) -> torch.Tensor:
    """Standard Gumbel noise (B, L), row b drawn from ``generators[b]`` only (the guards of
    :func:`gumbel_sample` keep u = 0 finite)."""
    uniform_BL = torch.stack(
        [torch.rand(length, generator=generator, device=device, dtype=torch.float32) for generator in generators]
    )
    return -torch.log(-torch.log(uniform_BL + 1e-30) + 1e-30)


def timesteps_for_mask_ratio(schedule: Any, masked_fraction_B: torch.Tensor) -> torch.Tensor:
    """The step t in [0, T-1] whose expected mask ratio gamma_bar_t is closest to each row's masked fraction
    (B,) -> long (B,) on the fraction's device.

    Purity and confidence decoding do not follow the chain's timesteps, but the denoiser was trained on
    x_t ~ q(x_t | x_0), where a fraction gamma_bar_t of tokens is masked: feeding the t that matches the
    actual fraction keeps its input in distribution.  Ties go to the smaller t.  A schedule without a
    ``gamma_bar`` table is taken as linear, gamma_bar_t = (t + 1) / T.
    """
    num_steps = schedule.num_steps
    gamma_bar = getattr(schedule, "gamma_bar", None)
    if gamma_bar is None:
        gamma_bar_T = torch.arange(1, num_steps + 1, dtype=torch.float64) / num_steps
    else:
        # The last entry (index T) is step -1, "no noise", which the denoiser never sees.
        gamma_bar_T = torch.as_tensor(gamma_bar, dtype=torch.float64).cpu()[:num_steps]
    fraction_B = masked_fraction_B.detach().to("cpu", torch.float64)
    t_B = (gamma_bar_T.view(1, -1) - fraction_B.view(-1, 1)).abs().argmin(dim=1)
    return t_B.to(masked_fraction_B.device)


def _ranks(score_BL: torch.Tensor, descending: bool) -> torch.Tensor:
    """Each position's rank (0 = first) in its row when sorted by ``score_BL`` (stable: ties keep position
    order, so the choice is deterministic)."""
    order_BL = torch.sort(score_BL, dim=1, descending=descending, stable=True).indices
    positions_BL = torch.arange(score_BL.shape[1], device=score_BL.device).expand_as(order_BL)
    return torch.empty_like(order_BL).scatter_(1, order_BL, positions_BL)


# -- posterior: the reverse chain with strided timesteps --------------------------------------------


def strided_timesteps(num_steps: int, steps: int) -> list[int]:
    """``steps`` timesteps evenly spaced from T-1 down to 0: t_i = round((T-1)(S-1-i)/(S-1)), rounding
    halves up, so [T-1] for S = 1, [T-1, 0] for S = 2 and T-1, T-2, ..., 0 for S = T.

    Strictly decreasing with no duplicates: for S <= T the spacing (T-1)/(S-1) is >= 1, and rounding
    halves up maps values 1 or more apart to distinct integers.  Integer arithmetic, so no float
    rounding decides a tie.
    """
    steps = check_steps(steps, num_steps)
    if steps == 1:
        return [num_steps - 1]
    span, intervals = num_steps - 1, steps - 1
    return [(2 * span * (intervals - i) + intervals) // (2 * intervals) for i in range(steps)]


#: Replacement mass K * beta_bar_{T-1} above which keeping revealed tokens is no longer exact (the
#: released schedule has 1e-6: in effect pure masking).
REPLACE_NOISE_WARNING = 1e-3


class KeepUnmaskedWarning(VqtouchWarning):
    """``keep_unmasked`` with a schedule whose replacement noise makes revealed tokens provisional."""


class PosteriorSampler(Sampler):
    """VQ-Diffusion's reverse chain over ``steps`` strided timesteps (:func:`strided_timesteps`).

    At each point t_i: p(x0 | x_t) = denoise(x_t, t_i), then x_s ~ posterior(p(x0 | x_t), x_t, t_i, s) with
    s = t_{i+1}, the next point, and s = -1 after the last one (x_{-1} is x_0 itself, drawn with MASK
    excluded).  The jump t -> s is the exact multi-step posterior of the forward process, not VQ-Diffusion's
    fast approximation (network at t, posterior at t - skip).  ``steps`` denoise calls; steps = 1 is one
    draw from p(x0 | all MASK), steps = T is the full chain.
    """

    def __init__(self, keep_unmasked: bool = True) -> None:
        #: Keep revealed tokens fixed (see :class:`PosteriorSamplerConfig`).
        self.keep_unmasked = keep_unmasked

    @torch.no_grad()
    def sample(
        self, denoise: Denoise, schedule: Any, *, length: int, steps: int, generators: list[torch.Generator]
    ) -> torch.Tensor:
        """Codes (B, length) in [0, K) for B = len(generators), from all MASK in ``steps`` denoise calls."""
        codes_BL = _all_mask(schedule, length, steps, generators)
        mask_index, batch, device = schedule.mask_index, len(generators), codes_BL.device
        if self.keep_unmasked and hasattr(schedule, "replace_mass"):
            replace = float(schedule.replace_mass(schedule.num_steps - 1))
            if replace > REPLACE_NOISE_WARNING:
                warnings.warn(
                    f"the posterior sampler keeps revealed tokens (keep_unmasked=true) but this schedule "
                    f"has real replacement noise ({replace:.3g} at the last step): revealed tokens are then "
                    "not final and keeping them biases samples (measured 0.04-0.1 per token); set "
                    "generator.sampler.keep_unmasked=false",
                    KeepUnmaskedWarning,
                    stacklevel=2,
                )
        points = strided_timesteps(schedule.num_steps, steps)
        for i, t in enumerate(points):
            s = points[i + 1] if i + 1 < len(points) else -1
            t_B = torch.full((batch,), t, dtype=torch.long, device=device)
            log_x0_BCL = _denoise(denoise, codes_BL, t_B, schedule.num_codes + 1)
            log_xs_BCL = schedule.posterior(log_x0_BCL, codes_BL, t_B, torch.full_like(t_B, s))
            if s == -1:
                log_xs_BCL = _without_mask(log_xs_BCL, mask_index)
            drawn_BL = gumbel_sample(log_xs_BCL, generator=generators)
            codes_BL = torch.where(codes_BL == mask_index, drawn_BL, codes_BL) if self.keep_unmasked else drawn_BL
        return codes_BL


# -- purity: Improved VQ-Diffusion's high-quality inference -----------------------------------------


def linear_masked_counts(length: int, steps: int) -> list[int]:
    """Tokens still masked after each of ``steps`` purity rounds: L - floor(L (i+1) / S), so each round
    reveals floor(L/S) or ceil(L/S) tokens (the larger counts last, when the context is richest) and all
    L are revealed after round S-1.

    Linear, as Improved VQ-Diffusion's fixed number of tokens per step.  With S > L some rounds reveal
    nothing; the sampler skips them without calling denoise.
    """
    return [length - (length * (i + 1)) // steps for i in range(steps)]


class PuritySampler(Sampler):
    """Improved VQ-Diffusion's purity sampling: ``steps`` rounds, each revealing the masked tokens of highest
    (noised) purity, max_k p(x0 = k | x_t), with the count of :func:`linear_masked_counts`.

    Revealed tokens take a Gumbel draw of p(x0 | x_t) at their position and are never changed again.  The
    timestep given to denoise is the one whose gamma_bar matches the masked fraction
    (:func:`timesteps_for_mask_ratio`).  ``min(steps, L)`` denoise calls.
    """

    def __init__(self, randomness: float = 1.0) -> None:
        #: Gumbel noise scale on log-purity (see :class:`PuritySamplerConfig`).
        self.randomness = randomness

    @torch.no_grad()
    def sample(
        self, denoise: Denoise, schedule: Any, *, length: int, steps: int, generators: list[torch.Generator]
    ) -> torch.Tensor:
        """Codes (B, length) in [0, K) for B = len(generators), from all MASK in ``min(steps, length)`` calls."""
        codes_BL = _all_mask(schedule, length, steps, generators)
        mask_index, num_codes, device = schedule.mask_index, schedule.num_codes, codes_BL.device
        for masked_after in linear_masked_counts(length, steps):
            is_masked_BL = codes_BL == mask_index
            masked_B = is_masked_BL.sum(dim=1)
            reveal_B = (masked_B - masked_after).clamp_min(0)
            if int(reveal_B.max()) == 0:
                continue  # only when steps > length: nothing to reveal, so no denoise call is wasted
            log_x0_BCL, drawn_BL = _draw_masked(denoise, schedule, codes_BL, masked_B, generators)
            score_BL = log_x0_BCL[:, :num_codes].amax(dim=1)
            if self.randomness > 0:
                score_BL = score_BL + self.randomness * _row_gumbel(generators, length, device)
            score_BL = score_BL.masked_fill(~is_masked_BL, float("-inf"))  # revealed tokens are never chosen
            reveal_BL = _ranks(score_BL, descending=True) < reveal_B.view(-1, 1)
            codes_BL = torch.where(reveal_BL, drawn_BL, codes_BL)
        return codes_BL


# -- confidence: MaskGIT decoding -------------------------------------------------------------------


def cosine_masked_target(length: int, steps: int, iteration: int) -> int:
    """MaskGIT's cosine schedule: floor(L cos(pi/2 (i+1)/S)) tokens should stay masked after iteration i
    (0 after the last).  The sampler clamps it to [0, #masked - 1] so each iteration reveals at least one."""
    if iteration >= steps - 1:
        return 0
    return math.floor(length * math.cos(math.pi / 2 * (iteration + 1) / steps))


class ConfidenceSampler(Sampler):
    """MaskGIT decoding (docs/diffusion.md section 4) of a VQ-Diffusion x0-predictor.

    Iteration i of ``steps``: draw every masked token from p(x0 | x_t) (Gumbel), score it by
    log p(drawn) + temperature (1 - (i+1)/S) Gumbel noise, and re-mask the
    min(:func:`cosine_masked_target`, #masked - 1) least confident draws; the last iteration keeps all.
    Revealed tokens stay fixed.  The timestep comes from the masked fraction as for ``purity``.  ``steps``
    denoise calls when steps <= L; with steps > L decoding ends once nothing is masked (at most L calls).
    """

    def __init__(self, temperature: float = 4.5) -> None:
        #: Choice temperature tau (see :class:`ConfidenceSamplerConfig`).
        self.temperature = temperature

    @torch.no_grad()
    def sample(
        self, denoise: Denoise, schedule: Any, *, length: int, steps: int, generators: list[torch.Generator]
    ) -> torch.Tensor:
        """Codes (B, length) in [0, K) for B = len(generators), from all MASK in at most ``steps`` calls."""
        codes_BL = _all_mask(schedule, length, steps, generators)
        mask_index, device = schedule.mask_index, codes_BL.device
        for i in range(steps):
            is_masked_BL = codes_BL == mask_index
            masked_B = is_masked_BL.sum(dim=1)
            if int(masked_B.max()) == 0:
                break  # only when steps > length: everything is revealed already
            log_x0_BCL, drawn_BL = _draw_masked(denoise, schedule, codes_BL, masked_B, generators)
            # The draws are never MASK, so their log-probability is read off the prediction as it is.
            confidence_BL = log_x0_BCL.gather(1, drawn_BL.unsqueeze(1)).squeeze(1)
            noise_scale = self.temperature * (1.0 - (i + 1) / steps)
            if noise_scale > 0:
                confidence_BL = confidence_BL + noise_scale * _row_gumbel(generators, length, device)
            # Revealed tokens are not candidates for re-masking.
            confidence_BL = confidence_BL.masked_fill(~is_masked_BL, float("inf"))
            target = cosine_masked_target(length, steps, i)
            keep_masked_B = torch.minimum(torch.full_like(masked_B, target), masked_B - 1).clamp_min(0)
            remask_BL = _ranks(confidence_BL, descending=False) < keep_masked_B.view(-1, 1)
            codes_BL = torch.where(is_masked_BL & ~remask_BL, drawn_BL, codes_BL)
        return codes_BL


# -- factories (registered in samplers_plugin.py) --------------------------------------------------


def build_posterior_sampler(config: PosteriorSamplerConfig, context: BuildContext) -> PosteriorSampler:
    """Factory of the ``posterior`` sampler (the context is not needed: the schedule comes at sampling)."""
    return PosteriorSampler(keep_unmasked=config.keep_unmasked)


def build_purity_sampler(config: PuritySamplerConfig, context: BuildContext) -> PuritySampler:
    """Factory of the ``purity`` sampler."""
    return PuritySampler(randomness=config.randomness)


def build_confidence_sampler(config: ConfidenceSamplerConfig, context: BuildContext) -> ConfidenceSampler:
    """Factory of the ``confidence`` sampler."""
    return ConfidenceSampler(temperature=config.temperature)

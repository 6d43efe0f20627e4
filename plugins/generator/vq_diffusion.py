"""The ``vq_diffusion`` generator: a VQ-Diffusion style discrete-diffusion decoder over the code grid.

The forward process, losses and guidance are in :mod:`.diffusion`, the x0-predicting network in
:mod:`.denoiser`; this module ties them into a :class:`vqtouch.core.Generator` plugin:

- training: x_t ~ q(x_t | x_0) at an (importance-sampled) step t, the network predicts x_0 from
  (x_t, t, condition tokens), and the loss is either the variational bound with the auxiliary
  x_0 term (``loss="vb"``) or the absorbing-state weighted cross-entropy on masked tokens
  (``loss="masked_ce"``);
- sampling: the condition is encoded once per call (cross-attention keys and values of every
  block), conditional and null rows run as one batch when guidance is on, guidance and
  truncation are applied to the x0 prediction, and a :class:`vqtouch.core.Sampler` plugin turns
  the predictions into codes.

All diffusion maths is fp32 whatever the autocast (the network's logits are fp32).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from vqtouch.core import BuildContext, ConditionTokens, ConfigError, Generator, Sampler
from vqtouch.core.image_size import ImageSize, image_hw

from .denoiser import DiffusionTransformer
from .diffusion import (
    MaskReplaceSchedule,
    TimestepSampler,
    guided_log_x0,
    log_predict_x0,
    masked_ce_loss,
    truncate,
    vb_loss,
)
from .vq_diffusion_plugin import VQDiffusionConfig


#: Where :meth:`VQDiffusion.masked_log_likelihood` reads the model, as fractions of the T steps.
LIKELIHOOD_FRACTIONS = (0.2, 0.4, 0.6, 0.8)


def likelihood_steps(num_steps: int) -> list[int]:
    """The distinct steps t in [1, T-1] at :data:`LIKELIHOOD_FRACTIONS` of ``num_steps`` = T."""
    return sorted({min(num_steps - 1, max(1, round(fraction * num_steps))) for fraction in LIKELIHOOD_FRACTIONS})


class VQDiffusion(Generator):
    """A discrete-diffusion generator of code grids, ``image_hw(code_grid)`` (rows, columns) (see the module
    docstring)."""

    def __init__(self, config: VQDiffusionConfig, codebook_size: int, code_grid: ImageSize, cond_dim: int) -> None:
        super().__init__()
        self.config = config
        self.num_codes = codebook_size
        self.grid_hw = image_hw(code_grid)
        try:
            self.schedule = MaskReplaceSchedule(
                codebook_size, config.num_steps, config.att_1, config.att_T, config.ctt_1, config.ctt_T
            )
        except ValueError as exc:
            raise ConfigError(f"generator 'vq_diffusion': {exc}") from None
        self.network = DiffusionTransformer(
            codebook_size,
            config.num_steps,
            self.grid_hw,
            cond_dim,
            depth=config.depth,
            width=config.width,
            heads=config.heads,
            mlp_ratio=config.mlp_ratio,
            dropout=config.dropout,
            mlp_conv=config.mlp_conv,
        )
        self.timesteps = TimestepSampler(config.num_steps)
        #: Says from the grid's embedding which cells hold the contact (``contact_weight``); None when off.
        self.contact_head = nn.Linear(config.width, 1) if config.contact_weight > 0 else None

    @property
    def max_steps(self) -> int:
        """The most sampling steps a call can take: the T steps of the forward process."""
        return self.config.num_steps

    @property
    def length(self) -> int:
        """Tokens per code grid, L = H W."""
        return self.grid_hw[0] * self.grid_hw[1]

    def _flatten(self, codes_BHW: torch.Tensor) -> torch.Tensor:
        if codes_BHW.shape[1:] != self.grid_hw:
            raise ValueError(
                f"vq_diffusion was built for {self.grid_hw[0]}x{self.grid_hw[1]} code grids; got "
                f"{tuple(codes_BHW.shape[1:])} (a tokenizer with another image size or downsampling)"
            )
        return codes_BHW.reshape(len(codes_BHW), -1).long()

    def training_loss(
        self,
        codes_BHW: torch.Tensor,
        condition: ConditionTokens,
        generator: torch.Generator | None = None,
        contact_BHW: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """The configured loss of one batch, averaged over the batch's tokens (VQ-Diffusion's scale).

        In training mode t is importance-sampled (when configured) and the sampler learns from
        the batch; in eval mode t is uniform and nothing is updated.  ``contact_BHW`` (bool, the
        code cells that hold the contact) adds ``contact_weight`` times :meth:`contact_loss` when the
        generator has a contact head and the condition a grid."""
        codes_BL = self._flatten(codes_BHW)
        batch = len(codes_BL)
        device = codes_BL.device
        # Held-out scoring (eval mode) draws t uniformly, so checkpoints are compared on equal terms.
        if self.config.importance_sampling and self.training:
            t_B, p_t_B = self.timesteps.sample(batch, generator)
        else:
            t_B = torch.randint(0, self.config.num_steps, (batch,), generator=generator, device=device)
            p_t_B = torch.full((batch,), 1.0 / self.config.num_steps, device=device)
        codes_t_BL = self.schedule.q_sample(codes_BL, t_B, generator)
        logits_BKL = self.network(codes_t_BL, t_B, condition=condition.tokens_BND, condition_grid=condition.grid_BDhw)
        masked = float((codes_t_BL == self.schedule.mask_index).float().mean())
        if self.config.loss == "vb":
            terms = vb_loss(
                log_predict_x0(logits_BKL),
                codes_BL,
                codes_t_BL,
                t_B,
                self.schedule,
                aux_weight=self.config.aux_weight,
                p_t_B=p_t_B,
            )
            loss_B, lt_B = terms.loss_B, terms.lt_B
        else:
            lt_B = masked_ce_loss(
                logits_BKL,
                codes_BL,
                codes_t_BL,
                t_B,
                self.schedule,
                weighting="mean" if self.config.loss == "masked_ce_mean" else "elbo",
            )
            loss_B = lt_B / p_t_B
        if self.training:
            self.timesteps.update(t_B, lt_B)
        # Divided by p_t (1/T for uniform t), so the mean is the per-token bound, as VQ-Diffusion logs it.
        loss = loss_B.sum() / (batch * self.length)
        scalars = {"lt": float(lt_B.detach().mean()), "masked_fraction": masked}
        if contact_BHW is not None and self.contact_head is not None and condition.grid_BDhw is not None:
            contact_loss = self.contact_loss(condition, contact_BHW)
            if contact_loss is not None:
                loss = loss + self.config.contact_weight * contact_loss
                scalars["contact_bce"] = float(contact_loss.detach())
        return loss, scalars

    def contact_parameters(self) -> list[nn.Parameter]:
        """What :meth:`contact_loss` trains of the generator: the grid embedding and the contact head
        (empty without a head); ``generator.train.grid_pretrain`` trains these alone."""
        if self.contact_head is None:
            return []
        return [*self.network.grid_proj.parameters(), *self.contact_head.parameters()]

    def contact_loss(self, condition: ConditionTokens, contact_BHW: torch.Tensor) -> torch.Tensor | None:
        """Binary cross-entropy (mean over cells) of the contact head on the condition grid's embedding
        against ``contact_BHW`` (bool, on the code grid), over the rows whose condition is not null;
        None when every row is null.  Why: a frozen or small conditioner's grid learns where the
        contact is only through the diffusion loss; asking its embedding for the place directly makes
        the place something the generator can read at each code (docs/generation.md)."""
        if self.contact_head is None or condition.grid_BDhw is None:
            raise ValueError("contact_loss needs generator.model.contact_weight > 0 and a condition with a grid")
        if tuple(contact_BHW.shape) != (len(condition.is_null_B), *self.grid_hw):
            raise ValueError(
                f"contact cells {tuple(contact_BHW.shape)} for {len(condition.is_null_B)} conditions on the "
                f"{self.grid_hw[0]}x{self.grid_hw[1]} code grid"
            )
        kept_B = ~condition.is_null_B.to(device=contact_BHW.device, dtype=torch.bool)
        if not bool(kept_B.any()):
            return None
        embedding_BLd = self.network.grid_embedding(condition.grid_BDhw[kept_B])
        logits_BL = self.contact_head(embedding_BLd.to(self.contact_head.weight.dtype)).squeeze(-1).float()
        target_BL = contact_BHW[kept_B].reshape(len(logits_BL), -1).float()
        return F.binary_cross_entropy_with_logits(logits_BL, target_BL)

    @torch.no_grad()
    def log_x0(self, codes_t_BL: torch.Tensor, t_B: torch.Tensor, condition: ConditionTokens) -> torch.Tensor:
        """log p(x0 | x_t, condition) (B, K+1, L) in fp32, without guidance or truncation."""
        return log_predict_x0(
            self.network(codes_t_BL, t_B, condition=condition.tokens_BND, condition_grid=condition.grid_BDhw)
        )

    @torch.no_grad()
    def masked_log_likelihood(self, codes_BHW: torch.Tensor, condition: ConditionTokens) -> torch.Tensor:
        """(B,) an estimate of log p(codes | condition) up to a constant shared by every condition: the sum,
        over the steps t at :data:`LIKELIHOOD_FRACTIONS` of T, of log p(x0 = code | x_t, condition) over
        the cells masked in x_t (each masked with probability gamma_bar_t).  Why these four reads rather
        than the variational bound's T: they are enough to rank candidates or conditions against each
        other (docs/generation.md), at four forward passes.  The masked cells of each t
        are drawn from a generator seeded by t alone and shared by every row, so two conditions or two
        candidates are compared on the same cells and a row's value does not depend on its batch."""
        codes_BL = self._flatten(codes_BHW)
        device = codes_BL.device
        self.eval()
        cache = self.network.precompute_condition(condition.tokens_BND, grid_BDhw=condition.grid_BDhw)
        total_B = torch.zeros(len(codes_BL), device=device)
        for t in likelihood_steps(self.config.num_steps):
            draws = torch.Generator(device=device).manual_seed(t)
            masked_L = torch.rand(self.length, generator=draws, device=device) < float(self.schedule.gamma_bar[t])
            codes_t_BL = torch.where(masked_L, self.schedule.mask_index, codes_BL)
            t_B = torch.full((len(codes_BL),), t, device=device)
            log_x0_BCL = log_predict_x0(self.network(codes_t_BL, t_B, cache=cache))
            total_B += (log_x0_BCL.gather(1, codes_BL[:, None]).squeeze(1) * masked_L).sum(1)
        return total_B

    @torch.no_grad()
    def sample(
        self,
        condition: ConditionTokens,
        sampler: Sampler,
        *,
        steps: int,
        null: ConditionTokens | None = None,
        guidance: float = 1.0,
        truncation: float = 1.0,
        generators: list[torch.Generator] | None = None,
    ) -> torch.Tensor:
        """Code grids (B, H, W) for a batch of conditions (see :meth:`vqtouch.core.Generator.sample`)."""
        batch = condition.tokens_BND.shape[0]
        guided = guidance != 1.0
        if guided and null is None:
            raise ValueError("guidance != 1 needs the null condition's tokens (null=...)")
        if generators is None:
            generators = [torch.Generator(device=condition.tokens_BND.device).manual_seed(row) for row in range(batch)]
        if len(generators) != batch:
            raise ValueError(f"got {len(generators)} generators for {batch} conditions")
        tokens_BMD, grid_BDhw = condition.tokens_BND, condition.grid_BDhw
        if guided:
            # Conditional and null rows run as one batch of 2B through the network; a null row's grid
            # is zeros (what the conditioner gives dropped rows in training).
            tokens_BMD = torch.cat([tokens_BMD, null.tokens_BND.to(tokens_BMD)])
            if grid_BDhw is not None:
                null_grid = null.grid_BDhw if null.grid_BDhw is not None else torch.zeros_like(grid_BDhw)
                grid_BDhw = torch.cat([grid_BDhw, null_grid.to(grid_BDhw)])
        self.eval()
        # Once per call, reused at every step.
        cache = self.network.precompute_condition(tokens_BMD, grid_BDhw=grid_BDhw)

        def denoise(codes_t_BL: torch.Tensor, t_B: torch.Tensor) -> torch.Tensor:
            if guided:
                logits_2BKL = self.network(torch.cat([codes_t_BL, codes_t_BL]), torch.cat([t_B, t_B]), cache=cache)
                log_cond_BCL, log_null_BCL = log_predict_x0(logits_2BKL).chunk(2)
                log_x0_BCL = guided_log_x0(log_cond_BCL, log_null_BCL, guidance)
            else:
                log_x0_BCL = log_predict_x0(self.network(codes_t_BL, t_B, cache=cache))
            return truncate(log_x0_BCL, truncation)

        codes_BL = sampler.sample(denoise, self.schedule, length=self.length, steps=steps, generators=generators)
        return codes_BL.view(batch, *self.grid_hw)


def build_vq_diffusion(config: VQDiffusionConfig, context: BuildContext) -> VQDiffusion:
    """Factory: the codebook size and the code grid come from the experiment's tokenizer (the context)."""
    if context.codebook_size < 2 or min(image_hw(context.code_grid)) < 1:
        raise ConfigError(
            "generator 'vq_diffusion' needs the tokenizer's codebook size and code grid "
            f"(the build context has codebook_size={context.codebook_size}, "
            f"code_grid={context.code_grid}); build it after the tokenizer"
        )
    return VQDiffusion(config, context.codebook_size, context.code_grid, context.cond_dim)

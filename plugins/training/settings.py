"""The training options every training stage's section holds (``tokenizer.train``, ``generator.train``).

Kept apart from :mod:`vqtouch.plugins.training.trainer` (the trainer, which needs torch) so that configs
validate, and ``vqtouch config`` runs, without importing torch."""

from __future__ import annotations

import math
from typing import Any, ClassVar, Literal

from pydantic import Field, field_validator
from pydantic_core import PydanticCustomError

from vqtouch.core.config import Section

#: Checkpoint folders are named ``step-NNNNNNNN`` (8 digits): the most steps a run can have.
MAX_STEPS = 99_999_999


class TrainConfig(Section):
    """How the trainer optimises one stage's task.

    Each training stage owns one of these in its own section (``tokenizer.train``, ...) and
    may subclass it to change defaults (VQGAN trains with Adam betas (0.5, 0.9)); these
    defaults are the usual AdamW ones.
    """

    #: The component this section trains (``"tokenizer"``, ``"generator"``): the key ``precision: auto``
    #: looks up in :data:`AUTO_PRECISION`.  Set by each stage's subclass; None: the device's default.
    component: ClassVar[str | None] = None

    # Counts are strict integers (true is not 1) and floats refuse booleans and strings: a
    # config value that validates must also train.
    steps: int = Field(
        1000,
        ge=0,
        le=MAX_STEPS,
        strict=True,
        description="Optimisation steps (at most 99999999: checkpoint folders have 8 digits).",
    )
    learning_rate: float = Field(1e-4, gt=0, le=10, strict=True, description="Peak learning rate.")
    weight_decay: float = Field(0.0, ge=0, le=1, strict=True, description="Decoupled weight decay (AdamW).")
    grad_clip: float | None = Field(
        1.0, gt=0, strict=True, description="Clip the gradient norm to this value; null disables."
    )
    precision: Literal["auto", "fp32", "bf16"] = Field(
        "auto",
        description="Autocast precision of the networks (quantizer and diffusion maths stay fp32): fp32, "
        "bf16, or auto, the measured choice for the component on the device the run trains on "
        "(AUTO_PRECISION: bf16 on a CPU with bf16 matrix units, fp32 on one without; bf16 on a CUDA GPU "
        "that supports it).",
    )
    optimizer: Literal["adamw", "adam"] = Field("adamw", description="Optimizer of every trained module.")
    warmup_steps: int = Field(
        0,
        ge=0,
        le=MAX_STEPS,
        strict=True,
        description="Raise the learning rate linearly from 1/warmup_steps of its peak to the "
        "peak over this many first steps (0: start at the peak).",
    )
    lr_schedule: Literal["constant", "cosine"] = Field(
        "constant",
        description="After warm-up: keep the peak learning rate ('constant') or lower it along a half "
        "cosine to min_lr_ratio of the peak at the last step ('cosine').",
    )
    min_lr_ratio: float = Field(
        0.1,
        ge=0.0,
        le=1.0,
        strict=True,
        description="Where the cosine schedule ends, as a share of the peak learning rate.",
    )
    betas: tuple[float, float] = Field((0.9, 0.999), description="Adam betas, each in [0, 1).")
    ema_decay: float | None = Field(
        None,
        gt=0.0,
        lt=1.0,
        strict=True,
        description="Keep an exponential moving average of the weights with this decay "
        "(saved next to the raw weights); null disables.",
    )
    ema_unbiased: bool = Field(
        True,
        strict=True,
        description="Average only the weights training produced: the average's weights "
        "decay**(n-k) are normalised by their sum, as Adam corrects its moments, so the initial "
        "(random) weights get no share.  false: the average starts at the initial weights, which keep "
        "decay**steps of it (13% after 2,000 steps at 0.999, enough to spoil a short run's samples).",
    )
    checkpoint_every: int = Field(
        500, ge=1, le=MAX_STEPS, strict=True, description="Write a checkpoint every this many steps."
    )
    log_every: int = Field(
        50,
        ge=1,
        le=MAX_STEPS,
        strict=True,
        description="Write metrics.jsonl every this many steps, and at the first and the last.",
    )
    max_skipped_steps: int = Field(
        20,
        ge=1,
        le=MAX_STEPS,
        strict=True,
        description="Abort after this many consecutive steps with a non-finite loss (each "
        "one is skipped and reported).",
    )
    keep_last: int = Field(
        3,
        ge=1,
        le=1_000_000,
        strict=True,
        description="Keep the newest this many complete checkpoints of the run; older step folders "
        "are deleted after each save (the one just written is always kept).",
    )
    keep_best: bool = Field(
        True,
        strict=True,
        description="At every checkpoint, score the held-out split with the task's validation "
        "loss (logged as val_loss) and keep the checkpoint with the lowest score too, "
        "beside the newest keep_last; `--step best` reads it.  Skipped when the run "
        "holds out no samples (data.val_fraction=0).",
    )

    # A validator, not a bounded type: stages redeclare ``betas`` with their own default
    # (TokenizerTrainConfig), and field validators apply to the redeclared field too.
    @field_validator("betas", mode="before")
    @classmethod
    def _no_boolean_betas(cls, value: Any) -> Any:
        if isinstance(value, (list, tuple)) and any(isinstance(item, bool) for item in value):
            raise _betas_error()
        return value

    @field_validator("betas")
    @classmethod
    def _betas_in_range(cls, value: tuple[float, float]) -> tuple[float, float]:
        # torch's Adam refuses anything else, but only once the trainer builds it; NaN fails too.
        if not all(0.0 <= beta < 1.0 for beta in value):
            raise _betas_error()
        return value


def learning_rate_factor(config: TrainConfig, step: int) -> float:
    """The share of the peak learning rate at ``step`` (0-based): a linear warm-up over
    ``warmup_steps``, then constant or a half cosine down to ``min_lr_ratio`` at step ``steps - 1``.
    A pure function of the step, so a resumed run continues the same schedule."""
    if step < config.warmup_steps:
        return (step + 1) / config.warmup_steps
    if config.lr_schedule == "constant":
        return 1.0
    span = max(1, config.steps - 1 - config.warmup_steps)
    progress_done = min(1.0, (step - config.warmup_steps) / span)
    return config.min_lr_ratio + (1.0 - config.min_lr_ratio) * 0.5 * (1.0 + math.cos(math.pi * progress_done))


def _betas_error() -> PydanticCustomError:
    return PydanticCustomError("betas_range", "each Adam beta must be a number in [0, 1), e.g. [0.9, 0.999]")

"""The ``tokenizer`` and ``reconstruct`` stages' plugin: the tokenizer section, its objective and optimiser
settings, and the stages' registration (the stages, in stages.py, are imported when they run)."""

from __future__ import annotations

from typing import ClassVar, Literal

from pydantic import Field, StrictFloat, StrictInt, field_validator

from vqtouch.core import Section, Slot, hookimpl
from vqtouch.plugins.training.settings import TrainConfig


class TokenizerLossConfig(Section):
    """The tokenizer objective: L1 + VQ + perceptual + adversarial (VQGAN's, with its safeguards)."""

    l1_weight: float = Field(1.0, ge=0.0, le=100.0, description="Weight of the L1 reconstruction loss.")
    codebook_weight: float = Field(1.0, ge=0.0, le=100.0, description="Weight of the quantizer's loss.")
    perceptual: Literal["none", "effnet_lite0", "lpips"] = Field(
        "effnet_lite0",
        description="Perceptual loss: 'lpips' needs user-supplied AlexNet and head weights; "
        "'effnet_lite0' is an offline feature loss on a real ImageNet network (not LPIPS).",
    )
    perceptual_weight: float = Field(0.1, ge=0.0, le=100.0, description="Weight of the perceptual loss.")
    perceptual_image_size: int = Field(
        96, ge=32, le=512, description="Side the images are resized to for the perceptual network."
    )
    lpips_backbone: str | None = Field(
        None, description="Path of alexnet-owt-7be5be79.pth (or VQTOUCH_LPIPS_BACKBONE)."
    )
    lpips_heads: str | None = Field(None, description="Path of LPIPS v0.1 alex.pth heads (or VQTOUCH_LPIPS_HEADS).")
    adversarial_weight: float = Field(
        0.8, ge=0.0, le=100.0, description="Weight of the hinge GAN loss (times the adaptive weight); 0 disables it."
    )
    disc_start: StrictInt | StrictFloat = Field(
        0.5,
        description="When the adversarial term and the discriminator start (neither trains before): a step "
        "(an integer, e.g. 2000) or a fraction of tokenizer.train.steps (a number below 1; 0.5: half way, "
        "once the autoencoder reconstructs).",
    )
    adaptive_weight_max: float = Field(1e4, gt=0.0, description="Upper clamp of the adaptive GAN weight.")

    @field_validator("disc_start")
    @classmethod
    def _a_step_or_a_fraction(cls, value: int | float) -> int | float:
        if not value >= 0:
            raise ValueError(f"disc_start is a step or a fraction of the run, at least 0; got {value}")
        if isinstance(value, float) and not value < 1:
            raise ValueError(f"{value} is a fraction of the run only below 1 (e.g. 0.5); give a step as an integer")
        return value


def disc_start_step(disc_start: int | float, steps: int) -> int:
    """The step at which the adversarial term starts in a run of ``steps`` steps (a fraction resolved)."""
    return int(disc_start * steps) if isinstance(disc_start, float) else disc_start


class TokenizerTrainConfig(TrainConfig):
    """How the tokenizer is optimised: the trainer's settings with VQGAN's Adam betas."""

    component: ClassVar[str | None] = "tokenizer"

    betas: tuple[float, float] = Field((0.5, 0.9), description="Adam betas (VQGAN uses (0.5, 0.9)).")


class TokenizerSection(Section):
    """The ``tokenizer`` stage's section: an autoencoder plugin plus a quantizer plugin, the
    objective and the optimiser settings."""

    autoencoder: Slot("autoencoder") | None = Field(None, description="Autoencoder plugin (e.g. dm_vqgan, vqgan).")
    quantizer: Slot("quantizer") | None = Field(None, description="Quantizer plugin (e.g. vq, ema_vq).")
    discriminator: Slot("discriminator") | None = Field(
        None, description="Discriminator plugin for the adversarial loss (e.g. patchgan); null trains without one."
    )
    loss: TokenizerLossConfig = Field(default_factory=TokenizerLossConfig, description="Training objective.")
    train: TokenizerTrainConfig = Field(default_factory=TokenizerTrainConfig, description="Optimisation settings.")


@hookimpl
def vqtouch_register_stages(register):
    register(
        "tokenizer",
        "vqtouch.plugins.tokenizer.stages:run_tokenizer_stage",
        section=TokenizerSection,
        needs=("data.dataset", "tokenizer.autoencoder", "tokenizer.quantizer"),
        uses=("tokenizer.discriminator", "metrics", "sensor"),
        makes=("tokenizer",),
        demo={"train.steps": 40, "train.checkpoint_every": 40, "train.log_every": 10},
        trains="train.steps",
        description="Train the tactile tokenizer (autoencoder + quantizer [+ GAN]) and score the held-out split.",
    )
    register(
        "reconstruct",
        "vqtouch.plugins.tokenizer.stages:run_reconstruct_stage",
        needs=("sensor", "tokenizer.autoencoder", "tokenizer.quantizer"),
        uses=("metrics",),
        description="Reconstruct the real reference frames of the experiment's sensor with the run's latest tokenizer.",
    )

"""The ``generator`` stage's plugin: its section, the generator's training options and their registration
(the stage, in stage.py, is imported when it runs)."""

from __future__ import annotations

import math
from typing import ClassVar, Literal

from pydantic import Field, field_validator, model_validator

from vqtouch.core import Section, Slot, hookimpl
from vqtouch.plugins.training.settings import TrainConfig


class GridPretrainConfig(Section):
    """``generator.train.grid_pretrain``: train the condition grid on the contact's place alone first."""

    steps: int = Field(
        0,
        ge=0,
        le=10_000_000,
        strict=True,
        description="Steps of the contact loss alone (generator.model.contact_weight's head on the condition "
        "grid) before the generator trains; each is one batch (data.batch_size) of one grid conditioner.  "
        "No diffusion runs, so a step costs a few per cent of a generator step.  0: off.",
    )
    new_scenes: int = Field(
        0,
        ge=0,
        le=1_000_000,
        strict=True,
        description="Newly rendered scenes added to the training split for these steps only (a dataset that "
        "renders scenes: the procedural one draws them from its seed + 1000, so none is a training or "
        "held-out sample).  Rendering and encoding them is part of the run's time.  0: the training split alone.",
    )
    learning_rate: float = Field(1e-3, gt=0, le=10, strict=True, description="AdamW learning rate of these steps.")
    weight_decay: float = Field(1e-4, ge=0, le=1, strict=True, description="AdamW decoupled weight decay.")
    conditioners: list[int] | None = Field(
        None,
        min_length=1,
        description="Which entries of generator.conditioners train (0-based; each must give a condition grid); "
        "steps take them in turn.  null: every conditioner whose condition has a grid.",
    )


class GeneratorTrainConfig(TrainConfig):
    """How the generator trains (``generator.train``); VQ-Diffusion's optimiser settings by default."""

    component: ClassVar[str | None] = "generator"

    steps: int = Field(2000, ge=0, le=99_999_999, strict=True, description="Optimisation steps.")
    learning_rate: float = Field(4.5e-4, gt=0, le=10, strict=True, description="Peak learning rate.")
    weight_decay: float = Field(4.5e-2, ge=0, le=1, strict=True, description="Decoupled weight decay (AdamW).")
    grad_clip: float | None = Field(
        0.5, gt=0, strict=True, description="Clip the gradient norm to this value; null disables."
    )
    betas: tuple[float, float] = Field((0.9, 0.96), description="Adam betas, each in [0, 1).")
    condition_dropout: float = Field(
        0.1,
        ge=0,
        lt=1,
        strict=True,
        description="Share of training rows whose condition is replaced by the learned "
        "null condition (needed for classifier-free guidance).",
    )
    canonical_background: bool = Field(
        True,
        description="Train on codes whose cells away from the contact are the no-contact image's own codes "
        "(vqtouch.plugins.generator.codes.canonical_background): the tokenizer gives identical "
        "no-contact patches different near-synonymous codes, which a generator would otherwise "
        "have to guess.  Needs the dataset's no-contact background; false: the raw codes.",
    )
    conditioner_weights: list[float] | None = Field(
        None,
        min_length=1,
        description="Share of the training steps each conditioner gets, in the order of "
        "generator.conditioners (any positive numbers; they are normalised), e.g. "
        "[2, 1, 1, 1] gives the first twice the steps of each other; null: equal "
        "shares.  Conditions that fix less of the image (a label) learn slower.",
    )
    grid_pretrain: GridPretrainConfig = Field(
        default_factory=GridPretrainConfig,
        description="Train the condition grid on the contact's place alone before the generator trains "
        "(steps: 0, off); see vqtouch.plugins.generator.grid_pretrain.",
    )
    code_cache: bool = Field(
        True,
        description="Reuse the tokenizer's codes of the dataset from the user cache "
        "folder when they were computed before (see "
        "vqtouch.plugins.generator.codes).",
    )

    @field_validator("conditioner_weights")
    @classmethod
    def _positive_finite(cls, weights: list[float] | None) -> list[float] | None:
        if weights is not None and not all(math.isfinite(w) and w > 0 for w in weights):
            raise ValueError(f"every conditioner weight must be a positive finite number, got {weights}")
        return weights


class GeneratorSection(Section):
    """The ``generator`` stage's section: the generator, its conditioners and sampler, how it trains
    and how the stage samples."""

    model: Slot("generator") | None = Field(None, description="Generator over the code grid (e.g. vq_diffusion).")
    conditioners: list[Slot("conditioner")] = Field(
        default_factory=list,
        description="Condition encoders the generator is trained with (label, tactile, "
        "clip, ...); each reads its own entry of a sample, one per training step.",
    )
    sampler: Slot("sampler") | None = Field(
        None, description="How codes are drawn from the generator (e.g. posterior, purity, confidence)."
    )
    sensor_tag: Slot("conditioner") | None = Field(
        None,
        description="A learned offset per sensor added to every condition (the `sensor` conditioner), so "
        "one generator draws several sensors' appearance; set by `vqtouch fewshot`, which trains it.  "
        "null: one sensor.",
    )
    sample_sensor: int = Field(
        0, ge=0, strict=True, description="Which sensor of sensor_tag sampling draws (vqtouch fewshot: 1, the new one)."
    )
    tokenizer_run: str | None = Field(
        None,
        description="Run directory of the trained tokenizer whose codes the "
        "generator learns, or a tokenizer checkpoint folder (e.g. "
        "from `vqtouch adapt`), or a bundle (pretrained:NAME); null: this run's own tokenizer stage.",
    )
    steps: int = Field(25, ge=1, le=1000, strict=True, description="Sampling steps (denoiser calls) per sample.")
    guidance: float = Field(1.0, ge=0, le=1000, description="Classifier-free guidance scale; 1 is unguided.")
    truncation: float = Field(
        1.0,
        gt=0,
        le=1,
        description="Keep only the most likely codes holding this much probability at each step; 1 keeps all.",
    )
    conditioner_guidance: dict[str, float] = Field(
        default_factory=dict,
        description="Default guidance per conditioner, by its name (e.g. {label: 2, visual: 2}): a condition "
        "that leaves the pose or texture open gains from guidance, one that pins both (touch) loses; "
        "conditioners not named use `guidance`.",
    )
    sample_precision: Literal["auto", "fp32", "bf16"] = Field(
        "auto",
        description="Autocast precision of the generator's network while it samples (the diffusion maths "
        "and the decoder stay fp32): auto, the measured choice for the device (bf16 on a CPU with bf16 "
        "matrix units or a CUDA GPU that supports it, else fp32), fp32 or bf16.",
    )
    sample_weights: Literal["ema", "raw"] = Field(
        "ema",
        description="Which weights sample: 'ema', the moving average training kept (train.ema_decay), when "
        "the checkpoint holds one, else the raw weights; 'raw', always the raw weights.",
    )
    num_samples: int = Field(
        16,
        ge=0,
        le=100_000,
        strict=True,
        description="Held-out conditions generated and scored after training (0: none).",
    )
    distribution: bool = Field(
        False,
        description="Also score the held-out samples' fd_effnetlite0 and the accuracy "
        "of a classifier trained on real images (EfficientNet-Lite0 "
        "features at 224 px; slower on a CPU).",
    )
    train: GeneratorTrainConfig = Field(default_factory=GeneratorTrainConfig, description="Optimisation settings.")

    @model_validator(mode="after")
    def _one_weight_per_conditioner(self) -> GeneratorSection:
        weights = self.train.conditioner_weights
        if weights is not None and len(weights) != len(self.conditioners):
            raise ValueError(
                f"train.conditioner_weights has {len(weights)} weights for {len(self.conditioners)} "
                "conditioners; give one per entry of generator.conditioners, in their order"
            )
        return self

    def guidance_for(self, conditioner_name: str) -> float:
        """The default guidance scale of the conditioner named ``conditioner_name``: its entry in
        ``conditioner_guidance``, else ``guidance``."""
        return float(self.conditioner_guidance.get(conditioner_name, self.guidance))

    @model_validator(mode="after")
    def _guidance_of_known_conditioners(self) -> GeneratorSection:
        names = [block.name for block in self.conditioners]
        for name, scale in self.conditioner_guidance.items():
            if name not in names:
                raise ValueError(
                    f"conditioner_guidance names {name!r}, which is none of generator.conditioners "
                    f"({', '.join(names) or 'none'}); key it by a conditioner's name"
                )
            if not (math.isfinite(scale) and 0 <= scale <= 1000):
                raise ValueError(f"conditioner_guidance[{name!r}] = {scale}: a guidance scale is in [0, 1000]")
        return self

    @model_validator(mode="after")
    def _sample_sensor_within_the_tag(self) -> GeneratorSection:
        if self.sensor_tag is not None:
            if self.sensor_tag.name != "sensor":
                raise ValueError(
                    f"generator.sensor_tag is the {self.sensor_tag.name!r} conditioner; it must be 'sensor' "
                    "(one learned offset per sensor)"
                )
            count = getattr(self.sensor_tag, "num_sensors", 2)
            if self.sample_sensor >= count:
                raise ValueError(
                    f"generator.sample_sensor={self.sample_sensor}, but sensor_tag has {count} sensors "
                    f"(0..{count - 1}); name one of them"
                )
        elif self.sample_sensor:
            raise ValueError("generator.sample_sensor is set but generator.sensor_tag is not; set both or neither")
        return self

    @model_validator(mode="after")
    def _contact_cells_need_the_canonical_background(self) -> GeneratorSection:
        if getattr(self.model, "contact_weight", 0) > 0 and not self.train.canonical_background:
            raise ValueError(
                "generator.model.contact_weight needs generator.train.canonical_background=true (the contact's "
                "cells are those whose canonical code is not the no-contact image's); set it or contact_weight=0"
            )
        return self

    @model_validator(mode="after")
    def _grid_pretraining_needs_the_contact_head(self) -> GeneratorSection:
        pretrain = self.train.grid_pretrain
        if pretrain.steps and getattr(self.model, "contact_weight", 0) <= 0:
            raise ValueError(
                "generator.train.grid_pretrain.steps > 0 trains the contact head, which "
                "generator.model.contact_weight > 0 builds; set contact_weight (e.g. 1) or grid_pretrain.steps=0"
            )
        outside = [i for i in pretrain.conditioners or () if not 0 <= i < len(self.conditioners)]
        if outside:
            raise ValueError(
                f"generator.train.grid_pretrain.conditioners names {outside}, outside generator.conditioners "
                f"(0..{len(self.conditioners) - 1})"
            )
        if pretrain.new_scenes and not pretrain.steps:
            raise ValueError(
                "generator.train.grid_pretrain.new_scenes is set but grid_pretrain.steps is 0; the new scenes "
                "serve only those steps: set steps or new_scenes=0"
            )
        return self

    @model_validator(mode="after")
    def _sampling_steps_within_the_model(self) -> GeneratorSection:
        # Checked with the config, not after training: sampling cannot take more steps than the model
        # has diffusion steps (a generator plugin without such a limit has no num_steps option).
        limit = getattr(self.model, "num_steps", None)
        if isinstance(limit, int) and self.steps > limit:
            raise ValueError(
                f"steps={self.steps} exceeds the generator's diffusion steps (generator.model.num_steps={limit}); "
                f"sample with at most {limit} steps or train a model with more"
            )
        return self


@hookimpl
def vqtouch_register_stages(register):
    register(
        "generator",
        "vqtouch.plugins.generator.stage:run_generator_stage",
        section=GeneratorSection,
        needs=(
            "data.dataset",
            "tokenizer.autoencoder",
            "tokenizer.quantizer",
            "generator.model",
            "generator.conditioners",
        ),
        uses=("generator.sampler", "metrics"),
        makes=("generator",),
        demo={"train.steps": 60, "train.checkpoint_every": 60, "train.log_every": 10, "num_samples": 8, "steps": 10},
        trains="train.steps",
        description="Train a generator over the tokenizer's codes, conditioned on a visual image, a tactile "
        "image, a label or text; then generate the held-out conditions and score them.",
    )

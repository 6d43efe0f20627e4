"""The interfaces that plugin components implement, and the context they are built with.

Core depends on none of the concrete models: it only knows these contracts.  Every
registry kind names one base class here, and :meth:`PluginHost.build` checks that a
factory returned an instance of it.  Components with weights are ``nn.Module`` s so that
one checkpoint writer (safetensors, no pickle) serves all of them.
"""

from __future__ import annotations

import abc
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from pydantic import BaseModel, ConfigDict, Field
from torch import nn

from .deprecations import warn_renamed
from .errors import ConfigError, unknown_name_message
from .image_size import ImageSize, ImageSizeOption, image_hw, square_or_pair


#: The sample keys whose condition is an image (the generation pipeline reads a path into a tensor).
IMAGE_SAMPLE_KEYS = ("tactile", "tactile_source", "visual")


class BuildContext(BaseModel):
    """Facts a factory needs that belong to the experiment rather than to the plugin.

    It is stored in every checkpoint header next to the plugin config, so a component can
    be rebuilt from the file alone.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    image_size: ImageSizeOption = Field(
        64, description="Size of the tactile images: S for S x S pixels, or (height, width)."
    )
    channels: int = Field(3, ge=1, le=16, description="Image channels (3 for RGB tactile images).")
    num_classes: int = Field(0, ge=0, description="Number of labels in the dataset (0 when unlabelled).")
    class_names: tuple[str, ...] = Field(
        (),
        description="The dataset's class names, indexed by label (empty when "
        "unlabelled or unknown): what a condition derived from the "
        "class (a material, a hardness) reads.",
    )
    cond_dim: int = Field(256, ge=1, description="Width of the condition tokens a conditioner must emit.")
    codebook_size: int = Field(0, ge=0, description="Codebook size of the tokenizer (0 when not yet known).")
    latent_dim: int = Field(
        0,
        ge=0,
        description="Channels of the autoencoder's latents, which the quantizer must match (0 when not yet known).",
    )
    code_grid: int | tuple[int, int] = Field(
        0,
        description="The tokenizer's code grid, image_size / the autoencoder's downsampling factor: S for S x S, "
        "or (rows, columns); 0 when not yet known.",
    )


class ProvidesContext:
    """Mixin of components that fix facts later components are built with.

    A dataset fixes the number of classes, an autoencoder the latent width a quantizer must
    match, a quantizer the codebook size a generator works with.  The assembly builds a
    provider before any component whose kind reads the fact (``RegistryKind.reads``).
    """

    def context_facts(self) -> dict[str, Any]:
        """``BuildContext`` fields this component determines, e.g. ``{"latent_dim": 32}``."""
        return {}


@dataclass
class ConditionTokens:
    """A batch of condition tokens for the generator.

    ``tokens_BND`` are the cross-attention tokens; ``is_null_B`` marks rows that carry the
    learned null condition (classifier-free guidance and condition dropout).  ``grid_BDhw``, from a
    conditioner whose condition is an image aligned with the target (a tactile image of the same
    contact, a visual image of it), is a feature map (B, cond_dim, h, w) over that image: a
    generator can add it at each position of its code grid, so it does not have to learn where
    the contact is through attention alone.  Null rows hold zeros there.  None for conditions
    without a spatial layout (label, text).
    """

    tokens_BND: torch.Tensor
    is_null_B: torch.Tensor
    grid_BDhw: torch.Tensor | None = None


def load_missing_as_zeros(module: nn.Module, *names: str) -> None:
    """Let ``module`` load a state dict that lacks the submodules ``names`` (checkpoints saved
    before they existed): their parameters load as zeros.  For layers added to a network as
    zero-initialised paths, so an old checkpoint computes exactly what it did.  Honoured by
    ``load_state_dict`` and by vqtouch's strict checkpoint loading."""
    module.vqtouch_zero_if_missing = tuple(getattr(module, "vqtouch_zero_if_missing", ())) + names

    def fill(state_dict: dict[str, torch.Tensor], prefix: str, *args: Any) -> None:
        fill_missing_with_zeros(module, state_dict, prefix)

    module._register_load_state_dict_pre_hook(fill)


def fill_missing_with_zeros(module: nn.Module, state_dict: dict[str, torch.Tensor], prefix: str = "") -> None:
    """Add zeros to ``state_dict`` for the tensors it lacks of every submodule declared with
    :func:`load_missing_as_zeros` anywhere in ``module`` (keys under ``prefix``)."""
    for path, child in module.named_modules():
        for name in getattr(child, "vqtouch_zero_if_missing", ()):
            for key, tensor in getattr(child, name).state_dict().items():
                full = ".".join(part for part in (path, name, key) if part)
                state_dict.setdefault(prefix + full, torch.zeros_like(tensor))


class Conditioner(nn.Module, abc.ABC):
    """Turns one kind of condition (label, visual image, tactile image, text) into tokens.

    Subclasses set ``sample_key`` (the key of a dataset sample they read, see
    :class:`TactileDataset`) and implement :meth:`encode`; the learned null token used for
    classifier-free guidance is shared by all of them.
    """

    #: Which entry of a sample (and so of a collated batch) this conditioner encodes: a built-in one
    #: (``"label"``, ``"visual"``, ``"tactile_source"`` (a paired sensor's image), ``"tactile"``,
    #: ``"text"``), any other entry a dataset provides, or the name of a condition derived from other
    #: entries (see :attr:`derived_from`).  ``vqtouch generate --condition KEY=VALUE`` gives it by this name.
    sample_key: ClassVar[str] = ""
    #: The sample entries a *derived* condition is computed from (e.g. ``("label",)`` for a material read
    #: from the class), when samples have no ``sample_key`` entry of their own; :meth:`derive` computes
    #: it.  Empty: the condition is the ``sample_key`` entry itself.
    derived_from: ClassVar[tuple[str, ...]] = ()

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        # 0.1.0 called it ``modality``: a conditioner written then still reads the right key.
        if "modality" in cls.__dict__ and "sample_key" not in cls.__dict__:
            warn_renamed(f"{cls.__name__}.modality", f"{cls.__name__}.sample_key", what="Conditioner attribute")
            cls.sample_key = cls.__dict__["modality"]

    def __init__(self, cond_dim: int, num_tokens: int) -> None:
        super().__init__()
        self.cond_dim = cond_dim
        self.num_tokens = num_tokens
        # Small non-zero init: a zero null token would make guided and unguided logits equal.
        self.null_tokens_ND = nn.Parameter(torch.randn(num_tokens, cond_dim) * 0.02)

    @abc.abstractmethod
    def encode(self, condition: Any) -> torch.Tensor:
        """Map a batch of raw conditions to tokens of shape (B, num_tokens, cond_dim)."""

    def encode_with_grid(self, condition: Any) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Tokens (B, num_tokens, cond_dim) and, for a condition image aligned with the target image,
        a feature map (B, cond_dim, h, w) over it (see :class:`ConditionTokens`).  The default has
        no grid: :meth:`encode` and None.  Image conditioners override this, computing both in one
        pass over the image."""
        return self.encode(condition), None

    def null(self, batch_size: int) -> ConditionTokens:
        """The learned 'no condition' tokens for ``batch_size`` rows (a conditioner with a grid gives
        its null rows a zero grid inside :meth:`forward`; generators treat a missing grid as zeros)."""
        tokens = self.null_tokens_ND.unsqueeze(0).expand(batch_size, -1, -1)
        return ConditionTokens(tokens, torch.ones(batch_size, dtype=torch.bool, device=tokens.device))

    def sample_entries(self) -> tuple[str, ...]:
        """The sample entries training reads for this conditioner: :attr:`derived_from`, else ``sample_key``."""
        return self.derived_from or (self.sample_key,)

    def condition_of(self, batch: dict[str, Any]) -> Any:
        """This conditioner's raw condition in a collated batch of samples: ``batch[sample_key]``, or for a
        derived condition, :meth:`derive` of its :attr:`derived_from` entries."""
        if self.sample_key in batch:
            return batch[self.sample_key]
        if self.derived_from and all(key in batch for key in self.derived_from):
            return self.derive(batch)
        wanted = " or ".join(repr(key) for key in (self.sample_key, *self.derived_from))
        raise KeyError(
            f"{type(self).__name__} reads samples' {wanted}, which this batch lacks "
            f"(keys: {', '.join(sorted(batch))}); use a dataset that provides it"
        )

    def derive(self, batch: dict[str, Any]) -> Any:
        """A derived condition of a collated batch from its :attr:`derived_from` entries (e.g. each row's
        material from its label, through the class names the build context carries).  Conditioners that
        set :attr:`derived_from` implement it."""
        raise NotImplementedError(
            f"{type(self).__name__} sets derived_from={self.derived_from}; it must implement derive(batch)"
        )

    def parse_condition(self, value: Any, *, image_size: ImageSize, class_names: Sequence[str] = ()) -> Any:
        """One sample's raw condition (what :meth:`condition_of` finds in one sample) from what a user
        gave, e.g. on ``vqtouch generate``'s command line; collate several with
        the trainer's ``collate_samples`` (``{sample_key: value}`` per sample).

        The default follows the sample keys of :class:`TactileDataset`: ``"tactile"``,
        ``"tactile_source"`` and ``"visual"`` take a (3, H, W) tensor in [0, 1] as it is (the generation
        pipeline reads an image file into one first), ``"label"`` takes a class
        index or one of ``class_names``, ``"text"`` takes the text.  A conditioner that reads
        another key overrides this.  Raises ConfigError saying what was wrong.
        """
        key = self.sample_key
        if key in IMAGE_SAMPLE_KEYS:
            if isinstance(value, torch.Tensor):
                return value
            raise ConfigError(
                f"{type(self).__name__} takes a (3, H, W) image tensor in [0, 1], got {type(value).__name__}; "
                "read an image file into one first (the generation pipeline does)"
            )
        if key == "label":
            text = str(value).strip()
            if text.lstrip("-").isdigit():
                label = int(text)
            elif text in class_names:
                label = list(class_names).index(text)
            else:
                raise ConfigError(f"--label: {unknown_name_message('class', text, class_names)} (or give an index)")
            if class_names and not 0 <= label < len(class_names):
                raise ConfigError(
                    f"--label {label}: out of range; this run's classes are 0..{len(class_names) - 1} "
                    f"({', '.join(class_names)})"
                )
            return label
        if key == "text":
            return str(value)
        raise NotImplementedError(
            f"{type(self).__name__} reads samples' {key!r}; it must override parse_condition "
            "to turn a user's value into that entry"
        )

    def forward(self, condition: Any, drop_mask_B: torch.Tensor | None = None) -> ConditionTokens:
        """Encode ``condition``; rows where ``drop_mask_B`` is True get the null tokens (and a zero grid)
        instead."""
        tokens_BND, grid_BDhw = self.encode_with_grid(condition)
        if tokens_BND.ndim != 3 or tokens_BND.shape[1:] != (self.num_tokens, self.cond_dim):
            raise RuntimeError(
                f"{type(self).__name__}.encode returned shape {tuple(tokens_BND.shape)}; "
                f"expected (B, {self.num_tokens}, {self.cond_dim})"
            )
        batch = tokens_BND.shape[0]
        if drop_mask_B is None:
            drop_mask_B = torch.zeros(batch, dtype=torch.bool, device=tokens_BND.device)
        null_BND = self.null_tokens_ND.to(tokens_BND.dtype).unsqueeze(0).expand(batch, -1, -1)
        tokens_BND = torch.where(drop_mask_B[:, None, None], null_BND, tokens_BND)
        if grid_BDhw is not None:
            if grid_BDhw.ndim != 4 or grid_BDhw.shape[:2] != (batch, self.cond_dim):
                raise RuntimeError(
                    f"{type(self).__name__}.encode_with_grid returned a grid of shape "
                    f"{tuple(grid_BDhw.shape)}; expected (B, {self.cond_dim}, h, w)"
                )
            grid_BDhw = torch.where(drop_mask_B[:, None, None, None], torch.zeros_like(grid_BDhw), grid_BDhw)
        return ConditionTokens(tokens_BND, drop_mask_B, grid_BDhw)


class SensorFamily(nn.Module, abc.ABC):
    """Renders tactile images from contact height maps for one family of sensors.

    Implementations are batched, run on any device and are deterministic for a given
    ``generator``.  A height map covers the sensor's imaged area (:meth:`imaged_extent_mm`: by
    default the square field of view, ``field_of_view_mm`` on a side) whatever its resolution,
    so scene generators can draw objects at physical scale.  A family with a background, a shaded contact response and
    per-sensor variants can subclass ``RenderedSensor`` from the built-in sensors package,
    which does that common work.
    """

    #: Side of the square imaged gel area in millimetres.  Scene generators draw objects at
    #: this physical scale, so a height map of any resolution covers exactly this area.
    field_of_view_mm: float = 15.0
    #: Short id of the physical sensor written into every sample's ``"sensor"`` field (e.g.
    #: ``"gelsight"``); empty means "use the registered plugin name".
    sensor_id: str = ""

    @abc.abstractmethod
    def render(self, height_mm_BHW: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """Render (B, H, W) indentation depths in millimetres to RGB images (B, 3, H, W) in [0, 1]."""

    def imaged_extent_mm(self, height: int, width: int) -> tuple[float, float]:
        """(rows, columns) in mm of the gel area an H x W image covers.  The default is the square
        field of view at every size (a non-square image then has non-square pixels); a family
        whose imaged area has its own aspect (GelSight's ``view: full``, 240 x 320) overrides it."""
        return self.field_of_view_mm, self.field_of_view_mm

    def reference_frames(self, height: int, width: int) -> torch.Tensor | None:
        """Real frames captured with the physical sensor this family models, as (N, 3, height, width)
        RGB in [0, 1] over the same imaged area as :meth:`render`, or None when the family ships none.

        Stages that check a tokenizer on real data (``reconstruct``) use these; a variant's
        perturbations are not applied (they are frames of the calibrated sensor itself).
        """
        return None


class Autoencoder(nn.Module, ProvidesContext, abc.ABC):
    """The autoencoder of a tokenizer: image -> latent grid -> image.

    Images are in [-1, 1]; latents are (B, latent_channels, H/f, W/f) with
    f = ``downsample_factor``.  The quantizer sits between :meth:`encode` and :meth:`decode`;
    :meth:`decode` is a pure function of its input.
    """

    downsample_factor: int = 1
    latent_channels: int = 1

    @abc.abstractmethod
    def encode(self, images_BCHW: torch.Tensor) -> torch.Tensor:
        """Images in [-1, 1] to latents (B, latent_channels, H/f, W/f)."""

    @abc.abstractmethod
    def decode(self, latents_BDhw: torch.Tensor) -> torch.Tensor:
        """Latents back to images in [-1, 1] (not clamped: losses see the raw output)."""

    def last_layer_weight(self) -> torch.Tensor | None:
        """The decoder's output-layer weight (for the GAN's adaptive weight), or None."""
        return None

    def learning_rate_scales(self) -> list[tuple[float, list[nn.Parameter]]]:
        """Parameter subsets that should train at ``scale`` times the base learning rate, as
        ``[(scale, params), ...]``; parameters not listed train at the base rate (the default: all)."""
        return []

    def reset_randomness(self) -> None:
        """Restart any evaluation-time randomness (e.g. MAE masks) so evaluations repeat exactly."""

    def context_facts(self) -> dict[str, Any]:
        """The latent width a quantizer must match and the code grid a generator works on."""
        facts: dict[str, Any] = {"latent_dim": self.latent_channels}
        spec = getattr(self, "vqtouch_spec", None)
        if spec is not None:
            height, width = image_hw(spec.context.image_size)
            facts["code_grid"] = square_or_pair(height // self.downsample_factor, width // self.downsample_factor)
        return facts


@dataclass
class QuantizerOutput:
    """What a quantizer returns for a batch of latents.

    ``quantized_BDhw`` carries straight-through gradients to the encoder; ``loss`` is the
    codebook + commitment loss (fp32 scalar); ``perplexity`` is exp(entropy) of the batch's
    code histogram; ``codes_Bhw`` are the integer codes.
    """

    quantized_BDhw: torch.Tensor
    codes_Bhw: torch.Tensor
    loss: torch.Tensor
    perplexity: torch.Tensor


class Quantizer(nn.Module, ProvidesContext, abc.ABC):
    """Maps continuous latents to codebook entries and integer codes (maths in fp32)."""

    codebook_size: int = 0
    embedding_dim: int = 0

    @abc.abstractmethod
    def forward(self, latents_BDhw: torch.Tensor) -> QuantizerOutput:
        """Quantise latents (B, embedding_dim, h, w)."""

    @abc.abstractmethod
    def lookup(self, codes_Bhw: torch.Tensor) -> torch.Tensor:
        """Codes (B, h, w) to quantised latents (B, embedding_dim, h, w), e.g. for generated codes."""

    def usage_counts(self) -> torch.Tensor | None:
        """How often each of the ``codebook_size`` codes was chosen since :meth:`reset_usage`, shape
        (K,), or None for quantizers without a codebook (e.g. ``identity``)."""
        return None

    def reset_usage(self) -> None:
        """Forget the code usage counted so far (before a pass that is reported on)."""

    def context_facts(self) -> dict[str, Any]:
        """The codebook size a generator over the codes works with."""
        return {"codebook_size": self.codebook_size}


class Discriminator(nn.Module, abc.ABC):
    """Scores images (B, C, H, W) in [-1, 1] as real or generated (logits of any shape, e.g. patches)."""

    @abc.abstractmethod
    def forward(self, images_BCHW: torch.Tensor) -> torch.Tensor:
        """Real/fake logits for each image (or patch)."""


class Clusterer(nn.Module, abc.ABC):
    """Groups feature vectors (e.g. per-sensor tokenizer features) into families."""

    @abc.abstractmethod
    def fit(self, features_NF: torch.Tensor) -> torch.Tensor:
        """Fit on (N, F) features and return the (N,) cluster index of each row."""

    @abc.abstractmethod
    def predict(self, features_NF: torch.Tensor) -> torch.Tensor:
        """Assign (N, F) features to fitted clusters; returns (N,) indices."""


class Metric(abc.ABC):
    """An accumulating image metric: ``update`` with batches, then ``compute``.

    A metric that cannot run here (a weights file or package it needs is missing) is built as a
    :class:`SkippedMetric` carrying the reason: it is reported as skipped, never replaced by a
    substitute under its name.  Score a set of metrics with :class:`MetricSet`, which does that.
    """

    higher_is_better: ClassVar[bool] = True
    #: Why this metric cannot be computed here (None: it can).  See :class:`SkippedMetric`.
    skipped: str | None = None

    @abc.abstractmethod
    def update(self, predicted_B3HW: torch.Tensor, target_B3HW: torch.Tensor) -> None:
        """Add a batch of images in [0, 1]."""

    @abc.abstractmethod
    def compute(self) -> float:
        """The metric over everything seen since the last reset."""

    @abc.abstractmethod
    def reset(self) -> None:
        """Forget what was seen."""


class SkippedMetric(Metric):
    """A metric that cannot run in this environment, and why (e.g. ``"needs vgg16-397923af.pth: ..."``).

    Factories return it instead of raising when only a user-supplied file or an optional package is
    missing, so one unavailable metric does not stop a run; :class:`MetricSet` reports it under
    ``"skipped"`` with the reason.  Updating or computing it raises :class:`ConfigError` with the reason.
    """

    def __init__(self, reason: str, higher_is_better: bool = True) -> None:
        if not reason.strip():
            raise ValueError("a skipped metric needs a reason that says what is missing and how to provide it")
        self.skipped = reason
        self.higher_is_better = higher_is_better  # type: ignore[misc]  # per instance: the real metric's direction

    def update(self, predicted_B3HW: torch.Tensor, target_B3HW: torch.Tensor) -> None:
        raise ConfigError(f"this metric is skipped: {self.skipped}")

    def compute(self) -> float:
        raise ConfigError(f"this metric is skipped: {self.skipped}")

    def reset(self) -> None:
        """Nothing to forget."""


class PerImageMetric(Metric):
    """A metric defined on each image pair and averaged over all pairs seen."""

    def __init__(self) -> None:
        self.reset()

    @abc.abstractmethod
    def per_image(self, predicted_B3HW: torch.Tensor, target_B3HW: torch.Tensor) -> torch.Tensor:
        """The metric of each pair, shape (B,)."""

    def update(self, predicted_B3HW: torch.Tensor, target_B3HW: torch.Tensor) -> None:
        values_B = self.per_image(predicted_B3HW, target_B3HW)
        self._sum += float(values_B.double().sum())
        self._count += values_B.numel()

    def compute(self) -> float:
        if self._count == 0:
            raise ValueError(f"{type(self).__name__}: no images were added before compute()")
        return self._sum / self._count

    def reset(self) -> None:
        self._sum, self._count = 0.0, 0


class Generator(nn.Module, abc.ABC):
    """Generates code grids conditioned on condition tokens (e.g. discrete diffusion).

    Built with the context's ``codebook_size`` and ``code_grid``; codes are integers in
    [0, codebook_size) on an ``image_hw(code_grid)`` grid (rows, columns).  Condition tokens come from the
    experiment's conditioners (:class:`ConditionTokens`; rows marked null carry the learned
    "no condition", which classifier-free guidance contrasts with).
    """

    @abc.abstractmethod
    def training_loss(
        self, codes_BHW: torch.Tensor, condition: ConditionTokens, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """The loss (scalar, fp32) of one batch of code grids under its conditions, and scalars to log.
        Random draws (timesteps, noise) come from ``generator``."""

    @abc.abstractmethod
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
        """Code grids (B, H, W) for a batch of conditions, drawn by ``sampler`` in ``steps`` steps.

        ``null``: the null condition's tokens for classifier-free guidance (``guidance`` != 1);
        ``truncation``: keep only the most likely codes holding this much probability at each
        step (1 keeps all); ``generators``: one per row, so a row's result does not depend on
        the batch it is in.
        """


class Sampler(abc.ABC):
    """How a discrete-diffusion generator turns its x0 predictions into codes (one plugin per
    strategy: the reverse posterior chain, MaskGIT-style confidence decoding, ...).

    A sampler sees only a ``denoise`` function: codes x_t (B, L) in [0, K] (K = MASK) and
    timesteps (B,) -> log p(x0 | x_t) (B, K+1, L), float32, already guided and truncated by the
    generator; and the generator's forward process (``schedule``, with ``num_codes``,
    ``num_steps``, ``mask_index`` and ``posterior``).  So guidance, truncation and condition
    caching are written once, in the generator, and a new sampler is one function.
    """

    @abc.abstractmethod
    def sample(
        self,
        denoise: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
        schedule: Any,
        *,
        length: int,
        steps: int,
        generators: list[torch.Generator],
    ) -> torch.Tensor:
        """Codes (B, length) in [0, K) for B = len(generators) rows, starting from all MASK and
        calling ``denoise`` about ``steps`` times; row b's random draws come from ``generators[b]``."""


@dataclass(frozen=True)
class BestOfBatch:
    """What a batch of best of K's candidates was drawn from, for the ranker that chooses among them.

    ``generator`` drew them and ``conditioner`` encoded their condition; ``conditions`` are the rows'
    raw conditions (``conditioner.condition_of`` of the batch): for a ranker with ``needs_classes``,
    the rows' class indices as a long tensor (B,) on the candidates' device."""

    generator: Any
    conditioner: Any
    conditions: Any = None


class BestOfRanker:
    """Chooses, for each row of a batch, which of best of K's candidate code grids to keep.

    A ranker implements :meth:`score` (higher is better; the earliest best candidate is kept) or, when
    it compares the candidates with each other, :meth:`choose`.  The generation pipeline that ranks with
    it calls :meth:`prepare` once first, with itself, so a ranker can read what it needs from the run
    (its tokenizer, its training split, ...).  Candidate 0 of a row is the row's own plain draw.
    """

    #: Whether it ranks by the rows' classes: only a conditioner over a finite set of classes (one with an
    #: integer ``num_classes``, the label's) then draws more than one candidate, and ``conditions`` are labels.
    needs_classes: ClassVar[bool] = False

    def prepare(self, pipeline: Any) -> None:
        """Read what ranking needs from the generation pipeline it ranks for (default: nothing)."""

    def score(self, codes_BHW: torch.Tensor, batch: BestOfBatch) -> torch.Tensor:
        """(B,) scores of one candidate per row, codes (B, H, W); higher is better."""
        raise NotImplementedError(
            f"{type(self).__name__}: a best-of ranker implements score(codes_BHW, batch) or "
            "choose(candidates_KBHW, batch)"
        )

    def choose(self, candidates_KBHW: torch.Tensor, batch: BestOfBatch) -> torch.Tensor:
        """(B,) long in [0, K): per row, the candidate to keep of ``candidates_KBHW`` (K, B, H, W).  The
        default scores each candidate with :meth:`score` and keeps the earliest of the highest."""
        chosen_B = best_B = None
        for index, codes_BHW in enumerate(candidates_KBHW):
            score_B = self.score(codes_BHW, batch).to(candidates_KBHW.device)
            if best_B is None:
                chosen_B, best_B = torch.zeros(len(score_B), dtype=torch.long, device=score_B.device), score_B
                continue
            better_B = score_B > best_B
            chosen_B = torch.where(better_B, index, chosen_B)
            best_B = torch.where(better_B, score_B, best_B)
        return chosen_B


class TactileDataset(ProvidesContext, abc.ABC):
    """A dataset of tactile samples, all readers and generators alike.

    ``__getitem__`` returns one sample dict:

    - ``"tactile"``: float tensor (3, H, W) in [0, 1] ((H, W) = ``image_hw`` of the configured image size);
    - ``"visual"``: float tensor (3, H, W) in [0, 1], only when the dataset pairs a visual image;
    - ``"tactile_source"``: float tensor (3, H, W) in [0, 1], only when the dataset pairs a second
      sensor's image of the same contact (the source image of touch-to-touch generation);
    - ``"label"``: int class index, -1 when the sample has none;
    - ``"text"``: str description, "" when the sample has none;
    - ``"sensor"``: str id of the sensor that produced the tactile image;
    - ``"id"``: str stable identifier (e.g. the relative path), used to pair results explicitly.

    A dataset may add keys of its own (the procedural scenes add ``"depth_mm"``, the press
    depth); stages rely only on the keys above.

    A dataset that knows which samples are near-duplicates of each other (the frames of one
    recording, the contacts of one trial) says so with :meth:`split_groups`, so that
    the data split (``split_dataset``) never puts one of them on each side of a split.
    """

    #: Class names indexed by label (empty for unlabelled datasets).
    class_names: list[str] = []
    #: What one group of :meth:`split_groups` is, in words ("recording", "trial", "fabric", ...);
    #: "sample" when every sample is its own group.
    split_unit: str = "sample"

    @property
    def num_classes(self) -> int:
        """Number of labels (0 when unlabelled)."""
        return len(self.class_names)

    def split_groups(self) -> list[str] | None:
        """Which samples must stay together in a train/held-out split: one group key per sample,
        in index order (samples with the same key go to the same side), or None when every sample
        is its own group.  The default is None; a reader that knows the recording, trial or object
        of each sample overrides it and sets :attr:`split_unit`."""
        return None

    def rendering_sensor(self) -> Any | None:
        """The sensor whose renders are this dataset's tactile images, when the dataset makes them:
        its no-contact image is then known exactly.  None (the default) for datasets of captured
        frames, whose no-contact background is then estimated from the images themselves."""
        return None

    def context_facts(self) -> dict[str, Any]:
        """The number of labels a label conditioner must embed, and their names."""
        return {"num_classes": self.num_classes, "class_names": tuple(self.class_names)}

    @abc.abstractmethod
    def __len__(self) -> int:
        """Number of samples."""

    @abc.abstractmethod
    def __getitem__(self, index: int) -> dict[str, Any]:
        """One sample (see the class docstring for its keys)."""

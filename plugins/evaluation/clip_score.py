"""``clip_score``: how well generated tactile images agree with their conditions in CLIP space (CTTP-style).

The score of one generated image is the cosine similarity between its CLIP image embedding and the
CLIP embedding of the condition it was generated from:

- a visual image, or a paired sensor's tactile image (``visual``, ``tactile_source``, ``tactile``):
  that image's CLIP image embedding;
- a text (``text``): its CLIP text embedding;
- a label (``label``): the text embedding of the ``prompt`` option filled with the class name
  (``"a tactile sensor image of {label}"`` by default).

Generation scoring (:func:`vqtouch.plugins.generator.score_generation`, behind the generator
stage and ``vqtouch evaluate generation``) reports the mean as ``clip_score`` beside the same score
of every comparison it carries: the real ground-truth tactile images (``real_clip_score``), the
sensor's no-contact background image (``background_clip_score``), the tokenizer's reconstruction
(``ceiling_``), the nearest training image by condition (``retrieval_``) and the label's mean training
image (``class_mean_``).  A raw CLIP cosine between a tactile image and a text is small and has no
absolute scale (CLIP was trained on photographs): only its place between the background's and the
real images' scores means anything.  ``clip_top1`` (with the same comparisons) is a retrieval figure:
the share of generated images whose own condition is the most similar among the distinct conditions
scored together; the background's ``clip_top1`` is what always naming the same condition gets.  CLIP
sees the whole image, so there is no contact-region version of this score: a claim that one generator
is better rests on the contact-region scores (``contact_psnr``), this one says whether it follows
its condition.

The weights are a local open_clip checkpoint, the same file the ``clip`` and ``text`` conditioners
read and found the same way (the ``checkpoint`` option or ``vqtouch evaluate generation
--clip-checkpoint``, ``VQTOUCH_CLIP_CKPT``, ``VQTOUCH_WEIGHTS_DIR``); they are never downloaded.
Without the file, or without open_clip (the ``clip`` extra), the metric is built as a
:class:`~vqtouch.core.SkippedMetric` whose reason names the file and the ways to provide it.

As a plain image-pair metric (``update(predicted, target)``, what reconstruction scoring and every
other :class:`~vqtouch.plugins.evaluation.metric_set.MetricSet` user calls), the second image is taken
as the condition: the score is then the cosine between the two images' CLIP image embeddings, a
tactile condition's score.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from vqtouch.core import (
    BuildContext,
    ConfigError,
    Metric,
    MissingWeightsError,
    PerImageMetric,
    PluginError,
    SkippedMetric,
)
from vqtouch.plugins.utils.weights import WeightsSpec, resolve_weights

from .clip_score_plugin import ClipScoreConfig  # re-exported: its old home
from .metrics import check_pair
from .open_clip_towers import (
    OPEN_CLIP_ENV_VAR,
    OPEN_CLIP_FILENAMES,
    OPEN_CLIP_SOURCE,
    builtin_tokenizer,
    check_open_clip_architecture,
    clip_image_embeddings,
    clip_image_geometry,
    create_open_clip_model,
    import_open_clip,
)

#: The same open_clip checkpoint the clip and text conditioners read (it holds both towers), found the same way.
CLIP_SCORE_WEIGHTS = WeightsSpec(
    description="metric 'clip_score' (open_clip image and text encoders)",
    filenames=OPEN_CLIP_FILENAMES,
    env_var=OPEN_CLIP_ENV_VAR,
    source_url=OPEN_CLIP_SOURCE,
    config_hint="the clip_score metric's checkpoint option (e.g. --set metrics.4.checkpoint=PATH, 4 being its place "
    "in metrics) or `vqtouch evaluate generation --clip-checkpoint PATH`",
)

#: Result keys: the mean cosine, and the retrieval figure (see the module docstring).
SCORE_KEY = "clip_score"
TOP1_KEY = "clip_top1"


class UnembeddableCondition(Exception):
    """Conditions CLIP cannot embed (a kind it has no tower for, a missing label or text); the message says why."""


class ClipConditionScore(PerImageMetric):
    """Cosine similarity in CLIP space between generated images and their conditions (see the module
    docstring); as a pair metric, between the two images of each pair.  Higher is better, at most 1."""

    higher_is_better = True

    def __init__(
        self,
        clip_model: nn.Module,
        tokenizer: Any,
        prompt: str,
        batch_size: int = 32,
        texts_unavailable: str | None = None,
    ) -> None:
        """``clip_model``: a loaded open_clip model (kept frozen, in eval mode, float32); ``tokenizer``:
        its built-in tokenizer, or None with ``texts_unavailable`` saying why texts and labels cannot be
        embedded; ``prompt``: the label template; ``batch_size``: inputs per forward pass."""
        self.model = clip_model.float().eval().requires_grad_(False)
        self.tokenizer, self.prompt, self.batch_size = tokenizer, prompt, batch_size
        self.texts_unavailable = texts_unavailable
        self.size_hw, mean, std = clip_image_geometry(clip_model)
        self.mean_C, self.std_C = torch.tensor(mean), torch.tensor(std)
        super().__init__()

    # -- embeddings ------------------------------------------------------------------------------------

    @torch.no_grad()
    def image_embeddings(self, images_B3HW: torch.Tensor) -> torch.Tensor:
        """L2-normalised float32 CLIP image embeddings (B, E) of RGB images in [0, 1], on the images' device."""
        if images_B3HW.ndim != 4 or images_B3HW.shape[1] != 3:
            raise ValueError(f"clip_score needs RGB images (B, 3, H, W) in [0, 1], got {tuple(images_B3HW.shape)}")
        if not torch.isfinite(images_B3HW).all():
            raise ValueError("clip_score: images contain NaN or Inf")
        self.model.to(images_B3HW.device)
        return torch.cat(
            [
                clip_image_embeddings(self.model, chunk, self.size_hw, self.mean_C, self.std_C)
                for chunk in images_B3HW.split(self.batch_size)
            ]
        )

    @torch.no_grad()
    def text_embeddings(self, texts: Sequence[str]) -> torch.Tensor:
        """L2-normalised float32 CLIP text embeddings (B, E) of ``texts``, on the model's device; raises
        :class:`UnembeddableCondition` when the architecture's tokenizer is not available offline."""
        if self.tokenizer is None:
            raise UnembeddableCondition(self.texts_unavailable or "no tokenizer")
        device = next(self.model.parameters()).device
        embeddings = []
        for start in range(0, len(texts), self.batch_size):
            ids_BL = self.tokenizer(list(texts[start : start + self.batch_size])).to(device)
            embeddings.append(F.normalize(self.model.encode_text(ids_BL).float(), dim=-1, eps=1e-6))
        return torch.cat(embeddings)

    def label_prompts(self, labels: Any, class_names: Sequence[str]) -> list[str]:
        """The prompt of each label (class index): ``prompt`` filled with its class name."""
        labels = [int(label) for label in torch.as_tensor(labels).flatten().tolist()]
        if not class_names:
            raise UnembeddableCondition(
                "label conditions need the dataset's class names to be written as prompts, and this dataset has none"
            )
        outside = [label for label in labels if not 0 <= label < len(class_names)]
        if outside:
            raise UnembeddableCondition(
                f"label {outside[0]} is not a class of this dataset "
                f"(0..{len(class_names) - 1}; -1: an unlabelled sample)"
            )
        return [self.prompt.format(label=class_names[label]) for label in labels]

    def condition_embeddings(
        self, condition: Any, sample_key: str, class_names: Sequence[str] = ()
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """CLIP embeddings (B, E) of a batch of raw conditions (what ``conditioner.condition_of(batch)``
        gives for samples' ``sample_key``), then which distinct condition each row is (B,) and the first row
        of each distinct condition (U,), as :func:`distinct_rows` (equal labels, texts or images are one
        condition).  RGB images are embedded as images, texts as texts and
        ``label`` entries as prompts; anything else raises :class:`UnembeddableCondition`."""
        if sample_key == "label":
            texts = self.label_prompts(condition, class_names)
            return self.text_embeddings(texts), *distinct_rows(texts)
        if isinstance(condition, (list, tuple)) and condition and all(isinstance(text, str) for text in condition):
            if not all(text.strip() for text in condition):
                raise UnembeddableCondition(f"some conditions ({sample_key!r}) are empty texts")
            return self.text_embeddings(condition), *distinct_rows(list(condition))
        if isinstance(condition, torch.Tensor) and condition.ndim == 4 and condition.shape[1] == 3:
            return self.image_embeddings(condition), *distinct_rows(condition)
        raise UnembeddableCondition(
            f"conditions read from samples' {sample_key!r} cannot be embedded by CLIP: it "
            "embeds RGB images (visual, tactile_source), texts and labels (as prompts)"
        )

    # -- scores -------------------------------------------------------------------------------------------

    def per_image(self, predicted_B3HW: torch.Tensor, target_B3HW: torch.Tensor) -> torch.Tensor:
        """The pair form: cosine (B,) between each predicted image's CLIP image embedding and its target's,
        the target standing for a tactile condition."""
        check_pair(predicted_B3HW, target_B3HW, "clip_score")
        predicted_BE, target_BE = self.image_embeddings(torch.cat([predicted_B3HW, target_B3HW])).chunk(2)
        return (predicted_BE * target_BE).sum(dim=-1).clamp(-1, 1).double().cpu()

    def condition_scores(
        self,
        candidates: Mapping[str, torch.Tensor],
        condition: Any,
        sample_key: str,
        class_names: Sequence[str] = (),
        digits: int | None = 4,
    ) -> dict[str, Any]:
        """``{prefix}clip_score`` (mean cosine of each image with its own condition) and, given at least two
        distinct conditions, ``{prefix}clip_top1`` (share of images whose own condition is the most similar
        of the distinct ones) for each candidate image set ``{prefix: images (B, 3, H, W)}``, image i
        generated for condition i (see :meth:`condition_embeddings`); rounded to ``digits`` unless None.
        Conditions CLIP cannot embed give ``{"skipped": {"clip_score": why}}`` instead."""
        try:
            conditions_BE, which_B, first_rows_U = self.condition_embeddings(condition, sample_key, class_names)
        except UnembeddableCondition as why:
            return {"skipped": {SCORE_KEY: f"metric 'clip_score' cannot score these conditions: {why}"}}
        distinct_UE = conditions_BE[first_rows_U.to(conditions_BE.device)]  # one row per distinct condition
        scores: dict[str, Any] = {}
        for prefix, images_B3HW in candidates.items():
            if len(images_B3HW) != len(which_B):
                raise ValueError(
                    f"clip_score: {len(images_B3HW)} {prefix or 'generated '}images for {len(which_B)} conditions"
                )
            # A repeated image (the background, a class mean) is embedded once.
            image_rows_B, first_image_rows_U = distinct_rows(images_B3HW)
            images_BE = self.image_embeddings(images_B3HW[first_image_rows_U.to(images_B3HW.device)])
            images_BE = images_BE[image_rows_B.to(images_BE.device)].to(conditions_BE.device)
            values = {SCORE_KEY: float((images_BE * conditions_BE).sum(dim=-1).clamp(-1, 1).double().mean())}
            if len(distinct_UE) >= 2:
                nearest_B = (images_BE @ distinct_UE.T).argmax(dim=1)
                values[TOP1_KEY] = float((nearest_B == which_B.to(nearest_B.device)).double().mean())
            scores |= {
                prefix + key: round(value, digits) if digits is not None else value for key, value in values.items()
            }
        return scores


def distinct_rows(values: torch.Tensor | Sequence[str]) -> tuple[torch.Tensor, torch.Tensor]:
    """Which distinct value each row of ``values`` holds (rows of a tensor compared exactly, or strings):
    its number (B,), 0, 1, ... in order of first appearance, and the row (U,) where each number first
    appears."""
    if isinstance(values, torch.Tensor):
        keys: list[Any] = [row.tobytes() for row in values.detach().cpu().flatten(1).numpy()]
    else:
        keys = list(values)
    numbers: dict[Any, int] = {}
    first_rows: list[int] = []
    for row, key in enumerate(keys):
        if key not in numbers:
            numbers[key] = len(first_rows)
            first_rows.append(row)
    return torch.tensor([numbers[key] for key in keys], dtype=torch.long), torch.tensor(first_rows, dtype=torch.long)


def build_clip_score(config: ClipScoreConfig, context: BuildContext) -> Metric:
    """Factory for ``clip_score``: the open_clip model in the user's local file; skipped (naming the file
    and the ways to provide it) when the file or open_clip is missing, or the file holds other weights.
    An architecture open_clip does not know is a :class:`~vqtouch.core.ConfigError`."""
    try:
        path = resolve_weights(CLIP_SCORE_WEIGHTS, config.checkpoint)
        open_clip = import_open_clip("clip_score", kind="metric")
    except (MissingWeightsError, PluginError) as error:
        return SkippedMetric(str(error))
    check_open_clip_architecture(open_clip, config.architecture, "clip_score", kind="metric")
    try:
        model = create_open_clip_model(
            open_clip, config.architecture, path, config.model_overrides, "clip_score", kind="metric"
        )
    except MissingWeightsError as error:  # a file, but not this architecture's weights: as good as missing
        return SkippedMetric(str(error))
    tokenizer, texts_unavailable = None, None
    context_length = getattr(model, "context_length", None)
    if not isinstance(context_length, int) or not hasattr(model, "encode_text"):
        texts_unavailable = f"open_clip architecture {config.architecture!r} has no text tower"
    else:
        try:
            tokenizer = builtin_tokenizer(
                open_clip, config.architecture, context_length, config.model_overrides, "clip_score", kind="metric"
            )
        except ConfigError as error:  # images can still be scored; texts and labels are skipped with this reason
            texts_unavailable = str(error)
    return ClipConditionScore(model, tokenizer, config.prompt, config.batch_size, texts_unavailable)

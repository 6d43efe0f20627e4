"""open_clip's towers from a local weights file: importing open_clip, checking an architecture name,
building the model from the file (never downloading), its image preprocessing and its offline BPE
tokenizer.

The one open_clip path of vqtouch: the ``clip`` and ``text`` conditioners and the ``clip_score``
metric all load and preprocess through it, so a conditioner and the metric judging it see the same
network the same way.  It lives with the evaluation library (as the EfficientNet-Lite0 feature
network does), which conditioners may import and which imports no conditioner.  open_clip itself is
the optional ``clip`` extra, imported only by :func:`import_open_clip`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from vqtouch.core import ConfigError, MissingWeightsError, PluginError
from vqtouch.core.errors import unknown_name_message

#: The file names an open_clip checkpoint is found under, the variable that names it and where to get
#: it: one checkpoint holds both towers, so the clip and text conditioners and clip_score share them.
OPEN_CLIP_FILENAMES = ("open_clip_model.safetensors", "open_clip_pytorch_model.bin")
OPEN_CLIP_ENV_VAR = "VQTOUCH_CLIP_CKPT"
OPEN_CLIP_SOURCE = "the model's open_clip/Hugging Face page (e.g. laion/CLIP-ViT-B-32-laion2B-s34B-b79K)"


def clip_image_geometry(clip_model: nn.Module) -> tuple[tuple[int, int], tuple[float, ...], tuple[float, ...]]:
    """The (height, width) open_clip ``clip_model``'s image tower takes, and the per-channel mean and
    standard deviation it normalises images with (OpenAI's, unless the model carries its own)."""
    from open_clip.constants import OPENAI_DATASET_MEAN, OPENAI_DATASET_STD

    image_size = clip_model.visual.image_size  # an int for ResNets, a pair for ViTs
    size_hw = tuple(image_size) if isinstance(image_size, (tuple, list)) else (image_size, image_size)
    mean = getattr(clip_model.visual, "image_mean", None) or OPENAI_DATASET_MEAN
    std = getattr(clip_model.visual, "image_std", None) or OPENAI_DATASET_STD
    return size_hw, tuple(mean), tuple(std)


def clip_image_embeddings(
    clip_model: nn.Module,
    images_B3HW: torch.Tensor,
    size_hw: tuple[int, int],
    mean_C: torch.Tensor,
    std_C: torch.Tensor,
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """L2-normalised float32 CLIP image embeddings (B, E) of RGB images (B, 3, H, W) in [0, 1]: resized
    (bicubic, antialiased, squashed to the tower's ``size_hw`` rather than cropped, so a sensor's
    non-square frame is seen whole), normalised with ``mean_C``/``std_C`` (see
    :func:`clip_image_geometry`) and encoded by ``clip_model`` in ``dtype`` without gradients.  The one
    CLIP image preprocessing of vqtouch: the ``clip`` conditioner and the ``clip_score`` metric share it."""
    images = F.interpolate(
        images_B3HW.float(), size=size_hw, mode="bicubic", antialias=True, align_corners=False
    ).clamp(0, 1)
    images = (images - mean_C.to(images)[:, None, None]) / std_C.to(images)[:, None, None]
    with torch.no_grad():
        embedding_BE = clip_model.encode_image(images.to(dtype)).float()
    return F.normalize(embedding_BE, dim=-1, eps=1e-6)


def import_open_clip(conditioner: str = "clip", *, kind: str = "conditioner") -> Any:
    """Import open_clip, or raise :class:`PluginError` naming the extra that installs it.

    open_clip is an optional dependency (the ``clip`` extra): only the plugins built on it need
    it.  ``kind`` and ``conditioner``, the plugin's kind and registered name, start the one-line
    error message (``conditioner 'clip'``, ``conditioner 'text'``, ``metric 'clip_score'``).
    """
    try:
        import open_clip
    except ImportError as exc:
        if isinstance(exc, ModuleNotFoundError) and exc.name == "open_clip":
            raise PluginError(f"{kind} {conditioner!r} needs open_clip_torch: pip install 'vqtouch[clip]'") from None
        # Installed but broken, typically a torchvision that does not match torch: say so, not "install it".
        first_line = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise PluginError(
            f"{kind} {conditioner!r}: open_clip_torch is installed but does not import "
            f"({first_line}); reinstall it with a torchvision that matches torch: "
            "pip install 'vqtouch[clip]'"
        ) from None
    return open_clip


def check_open_clip_architecture(
    open_clip: Any, architecture: str, conditioner: str = "clip", *, kind: str = "conditioner"
) -> None:
    """Raise :class:`~vqtouch.core.ConfigError` (one line, with the closest names) unless ``architecture``
    is one of open_clip's model names; ``kind`` and ``conditioner`` (the plugin) start the message."""
    if architecture not in open_clip.list_models():
        raise ConfigError(
            f"{kind} {conditioner!r}: "
            + unknown_name_message("open_clip architecture", architecture, open_clip.list_models())
        )


def create_open_clip_model(
    open_clip: Any,
    architecture: str,
    path: Path,
    model_overrides: dict[str, Any],
    conditioner: str = "clip",
    *,
    kind: str = "conditioner",
) -> nn.Module:
    """Build open_clip's ``architecture`` (with ``model_overrides``) holding the weights of the local file
    ``path``; never downloads.  A file that does not hold that model's weights raises
    :class:`~vqtouch.core.MissingWeightsError` in one line; ``kind`` and ``conditioner`` (the plugin)
    start the message."""
    from safetensors import SafetensorError

    try:
        return open_clip.create_model(architecture, pretrained=str(path), **model_overrides)
    except Exception as exc:
        # Wrong keys or shapes, and files that are not weights at all: not safetensors, or not a tensor
        # file torch.load accepts (its UnpicklingError, matched by name: the package never imports pickle).
        if not (
            isinstance(exc, (RuntimeError, ValueError, KeyError, EOFError, SafetensorError))
            or type(exc).__name__ == "UnpicklingError"
        ):
            raise
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise MissingWeightsError(
            f"{kind} {conditioner!r}: {path} does not hold {architecture} weights ({first})"
        ) from None


def builtin_tokenizer(
    open_clip: Any,
    architecture: str,
    context_length: int,
    model_overrides: dict[str, Any],
    conditioner: str = "text",
    *,
    kind: str = "conditioner",
) -> Any:
    """open_clip's tokenizer for ``architecture``, which must be its built-in BPE ``SimpleTokenizer``
    (vocabulary shipped in the wheel, so it works offline) producing ``context_length`` ids per text.

    Raises :class:`~vqtouch.core.ConfigError` (one line, starting with ``kind`` and ``conditioner``,
    the plugin that asked) when the architecture's tokenizer or text tower would come from the
    Hugging Face Hub (``hf_tokenizer_name``/``hf_model_name``, SigLIP models), since vqtouch never
    downloads, or when it would shorten texts at random.
    """
    plugin = f"{kind} {conditioner!r}"
    text_cfg = {
        **(open_clip.get_model_config(architecture) or {}).get("text_cfg", {}),
        **model_overrides.get("text_cfg", {}),
    }
    hub_source = text_cfg.get("hf_tokenizer_name") or text_cfg.get("hf_model_name")
    if hub_source or "siglip" in architecture.lower():
        what = f"the Hugging Face tokenizer {hub_source!r}" if hub_source else "a SigLIP (Hugging Face) tokenizer"
        raise ConfigError(
            f"{plugin}: open_clip architecture {architecture!r} uses {what}, which would be "
            "downloaded; vqtouch never downloads: choose an architecture with open_clip's built-in BPE "
            "tokenizer (e.g. ViT-B-32)"
        )
    tokenizer = open_clip.get_tokenizer(
        architecture, context_length=context_length, **text_cfg.get("tokenizer_kwargs", {})
    )
    if not isinstance(tokenizer, open_clip.tokenizer.SimpleTokenizer):
        raise ConfigError(
            f"{plugin}: open_clip gave {type(tokenizer).__name__} for {architecture!r}, not "
            "its built-in BPE tokenizer; choose another architecture (e.g. ViT-B-32)"
        )
    if tokenizer.reduction_fn is not None:
        raise ConfigError(
            f"{plugin}: {architecture!r}'s tokenizer shortens long texts at random "
            "(tokenizer_kwargs.reduction_mask); remove it so a text always gives the same tokens"
        )
    return tokenizer

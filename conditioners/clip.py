"""Visual conditioner: a frozen open_clip image encoder loaded from a local file.

open_clip (and with it torchvision's model code) is imported only when this conditioner
is built, so scenes that do not condition on visual images never import it; it is the
optional extra ``clip`` (``pip install 'vqtouch[clip]'``).  The CLIP weights are held in a
:class:`vqtouch.core.frozen.FrozenModule`, so they are not copied into vqtouch checkpoints:
the checkpoint records the architecture and the file path, and only the trainable
projection is saved.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import torch
import torch.nn.functional as F
from pydantic import Field
from torch import nn

from vqtouch.core import BuildContext, Conditioner, PluginConfig, PluginError, WeightsSpec, hookimpl, resolve_weights
from vqtouch.core.frozen import FrozenModule

CLIP_WEIGHTS = WeightsSpec(
    description="conditioner 'clip' (frozen open_clip image encoder)",
    filenames=("open_clip_model.safetensors", "open_clip_pytorch_model.bin"),
    env_var="VQTOUCH_CLIP_CKPT",
    config_hint="the clip conditioner's checkpoint option (e.g. --set generator.conditioners.0.checkpoint=PATH)",
    source_url="the model's open_clip/Hugging Face page (e.g. laion/CLIP-ViT-B-32-laion2B-s34B-b79K)",
)


class ClipConditionerConfig(PluginConfig):
    """Options of the ``clip`` conditioner."""

    name: Literal["clip"] = "clip"
    architecture: str = Field("ViT-B-32", min_length=1,
                              description="open_clip model name whose weights the checkpoint file holds.")
    checkpoint: str | None = Field(
        None, description="Path to the open_clip weights (.safetensors/.pt/.bin); else VQTOUCH_CLIP_CKPT or "
                          "VQTOUCH_WEIGHTS_DIR. Never downloaded.")
    num_tokens: int = Field(4, ge=1, le=77, description="Condition tokens projected from the image embedding.")
    model_overrides: dict[str, Any] = Field(
        default_factory=dict, description="Keyword overrides passed to open_clip.create_model (e.g. a small "
                                          "vision_cfg for a custom-trained model); must match the checkpoint.")


class ClipConditioner(Conditioner):
    """Frozen CLIP image embedding (L2-normalised) -> trainable projection -> condition tokens."""

    sample_key = "visual"

    def __init__(self, clip_model: nn.Module, embed_dim: int, cond_dim: int, num_tokens: int) -> None:
        super().__init__(cond_dim, num_tokens)
        # Frozen, always in eval mode, out of state_dict and checkpoints, moved by .to() (see FrozenModule).
        self.encoder = FrozenModule(clip_model)
        self.clip_image_size, mean, std = clip_image_geometry(clip_model)
        self.register_buffer("mean_C", torch.tensor(mean, dtype=torch.float32), persistent=False)
        self.register_buffer("std_C", torch.tensor(std, dtype=torch.float32), persistent=False)
        self.project = nn.Linear(embed_dim, num_tokens * cond_dim)

    def encode(self, condition: torch.Tensor) -> torch.Tensor:
        """Visual images (B, 3, H, W) in [0, 1] to tokens (B, num_tokens, cond_dim)."""
        images = condition
        if images.ndim != 4 or images.shape[1] != 3:
            raise ValueError(f"clip conditioner expects RGB images (B, 3, H, W) in [0, 1], got {tuple(images.shape)}")
        embedding_BE = clip_image_embeddings(self.encoder.network, images, self.clip_image_size, self.mean_C,
                                             self.std_C, dtype=self.encoder.dtype)
        return self.project(embedding_BE).view(-1, self.num_tokens, self.cond_dim)


def clip_image_geometry(clip_model: nn.Module) -> tuple[tuple[int, int], tuple[float, ...], tuple[float, ...]]:
    """The (height, width) open_clip ``clip_model``'s image tower takes, and the per-channel mean and
    standard deviation it normalises images with (OpenAI's, unless the model carries its own)."""
    from open_clip.constants import OPENAI_DATASET_MEAN, OPENAI_DATASET_STD

    image_size = clip_model.visual.image_size  # an int for ResNets, a pair for ViTs
    size_hw = tuple(image_size) if isinstance(image_size, (tuple, list)) else (image_size, image_size)
    mean = getattr(clip_model.visual, "image_mean", None) or OPENAI_DATASET_MEAN
    std = getattr(clip_model.visual, "image_std", None) or OPENAI_DATASET_STD
    return size_hw, tuple(mean), tuple(std)


def clip_image_embeddings(clip_model: nn.Module, images_B3HW: torch.Tensor, size_hw: tuple[int, int],
                          mean_C: torch.Tensor, std_C: torch.Tensor,
                          dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """L2-normalised float32 CLIP image embeddings (B, E) of RGB images (B, 3, H, W) in [0, 1]: resized
    (bicubic, antialiased, squashed to the tower's ``size_hw`` rather than cropped, so a sensor's
    non-square frame is seen whole), normalised with ``mean_C``/``std_C`` (see
    :func:`clip_image_geometry`) and encoded by ``clip_model`` in ``dtype`` without gradients.  The one
    CLIP image preprocessing of vqtouch: the ``clip`` conditioner and the ``clip_score`` metric share it."""
    images = F.interpolate(images_B3HW.float(), size=size_hw, mode="bicubic", antialias=True,
                           align_corners=False).clamp(0, 1)
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
            raise PluginError(f"{kind} {conditioner!r} needs open_clip_torch: "
                              "pip install 'vqtouch[clip]'") from None
        # Installed but broken, typically a torchvision that does not match torch: say so, not "install it".
        first_line = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise PluginError(f"{kind} {conditioner!r}: open_clip_torch is installed but does not import "
                          f"({first_line}); reinstall it with a torchvision that matches torch: "
                          "pip install 'vqtouch[clip]'") from None
    return open_clip


def check_open_clip_architecture(open_clip: Any, architecture: str, conditioner: str = "clip", *,
                                 kind: str = "conditioner") -> None:
    """Raise :class:`~vqtouch.core.ConfigError` (one line, with the closest names) unless ``architecture``
    is one of open_clip's model names; ``kind`` and ``conditioner`` (the plugin) start the message."""
    from vqtouch.core import ConfigError

    if architecture not in open_clip.list_models():
        from vqtouch.core.errors import unknown_name_message

        raise ConfigError(f"{kind} {conditioner!r}: " + unknown_name_message(
            "open_clip architecture", architecture, open_clip.list_models()))


def create_open_clip_model(open_clip: Any, architecture: str, path: Path, model_overrides: dict[str, Any],
                           conditioner: str = "clip", *, kind: str = "conditioner") -> nn.Module:
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
        if not (isinstance(exc, (RuntimeError, ValueError, KeyError, EOFError, SafetensorError))
                or type(exc).__name__ == "UnpicklingError"):
            raise
        from vqtouch.core import MissingWeightsError

        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise MissingWeightsError(f"{kind} {conditioner!r}: {path} does not hold {architecture} weights "
                                  f"({first})") from None


def build_clip_conditioner(config: ClipConditionerConfig, context: BuildContext) -> ClipConditioner:
    """Factory: import open_clip (the ``clip`` extra), resolve the local weights file (never downloads), then
    build the frozen encoder."""
    open_clip = import_open_clip()
    path = resolve_weights(CLIP_WEIGHTS, config.checkpoint)
    check_open_clip_architecture(open_clip, config.architecture)
    model = create_open_clip_model(open_clip, config.architecture, path, config.model_overrides)
    embed_dim = getattr(model.visual, "output_dim", None)
    if not isinstance(embed_dim, int):
        with torch.no_grad():
            size = model.visual.image_size
            size = size if isinstance(size, (tuple, list)) else (size, size)
            embed_dim = model.encode_image(torch.zeros(1, 3, *size)).shape[-1]
    return ClipConditioner(model, embed_dim, context.cond_dim, config.num_tokens)


@hookimpl
def vqtouch_register_conditioners(register):
    register("clip", build_clip_conditioner, ClipConditionerConfig,
             description="Frozen open_clip image encoder from a local file + trainable projection (vision-to-touch).")

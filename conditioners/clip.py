"""Visual conditioner: a frozen open_clip image encoder loaded from a local file.

open_clip (and with it torchvision's model code) is imported only when this conditioner
is built, so scenes that do not condition on visual images never import it; it is the
optional extra ``clip`` (``pip install 'vqtouch[clip]'``).  The CLIP weights are held in a
:class:`vqtouch.plugins.utils.frozen.FrozenModule`, so they are not copied into vqtouch checkpoints:
the checkpoint records the architecture and the file path, and only the trainable
projection is saved.
"""

from __future__ import annotations

import torch
from torch import nn

from vqtouch.core import BuildContext, Conditioner
from vqtouch.plugins.utils.weights import WeightsSpec, resolve_weights
from vqtouch.plugins.utils.frozen import FrozenModule
from vqtouch.plugins.evaluation.open_clip_towers import (
    OPEN_CLIP_ENV_VAR,
    OPEN_CLIP_FILENAMES,
    OPEN_CLIP_SOURCE,
    check_open_clip_architecture,
    clip_image_embeddings,
    clip_image_geometry,
    create_open_clip_model,
    import_open_clip,
)

from .clip_plugin import ClipConditionerConfig

CLIP_WEIGHTS = WeightsSpec(
    description="conditioner 'clip' (frozen open_clip image encoder)",
    filenames=OPEN_CLIP_FILENAMES,
    env_var=OPEN_CLIP_ENV_VAR,
    config_hint="the clip conditioner's checkpoint option (e.g. --set generator.conditioners.0.checkpoint=PATH)",
    source_url=OPEN_CLIP_SOURCE,
)


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
        embedding_BE = clip_image_embeddings(
            self.encoder.network, images, self.clip_image_size, self.mean_C, self.std_C, dtype=self.encoder.dtype
        )
        return self.project(embedding_BE).view(-1, self.num_tokens, self.cond_dim)


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

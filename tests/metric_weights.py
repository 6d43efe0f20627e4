"""Weight files of the real layouts, filled with random tensors, for the metrics that need user files.

No wheel ships torchvision's VGG16 / AlexNet or torch-fidelity's Inception-v3 weights, and the
suite never downloads.  These files exercise every loader, layout check and metric computation;
they are not pretrained, so the numbers they give are not LPIPS or FID values.  Their sha256
cannot match the real files' prefixes: :func:`accept_fabricated` lets a test accept the file's own.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from unittest import mock

import torch
from torch import nn


def _variance_preserving(module: nn.Module, generator: torch.Generator) -> None:
    """He-normal convolutions and linears, so activations neither vanish nor explode through deep stacks
    (default init shrinks them: torch-fidelity's Inception would output ~1e-8 features)."""
    for layer in module.modules():
        if isinstance(layer, (nn.Conv2d, nn.Linear)):
            fan_in = layer.weight[0].numel()
            with torch.no_grad():
                layer.weight.copy_(torch.randn(layer.weight.shape, generator=generator) * math.sqrt(2 / fan_in))


def fabricated_torchvision(folder: Path, architecture: str) -> Path:
    """torchvision's ``vgg16`` or ``alexnet`` state dict with random weights, named as the real file."""
    import torchvision

    filename = {"vgg16": "vgg16-397923af.pth", "alexnet": "alexnet-owt-7be5be79.pth"}[architecture]
    path = folder / "fabricated" / filename
    if not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        model = getattr(torchvision.models, architecture)(weights=None)
        _variance_preserving(model, torch.Generator().manual_seed(0))
        torch.save(model.state_dict(), path)
    return path


def fabricated_inception(folder: Path) -> Path:
    """torch-fidelity's Inception-v3 state dict (every key and shape of the real file), random weights."""
    from torchmetrics.image.fid import NoTrainInceptionV3

    path = folder / "fabricated" / "weights-inception-2015-12-05-6726825d.pth"
    if not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        # The network loads its weights in __init__ (downloading them by default): build it without loading.
        with (
            mock.patch("torch_fidelity.feature_extractor_inceptionv3.load_state_dict_from_url", lambda *a, **k: {}),
            mock.patch.object(nn.Module, "load_state_dict", lambda self, *a, **k: None),
        ):
            network = NoTrainInceptionV3(name="inception-v3-compat", features_list=["2048"])
        _variance_preserving(network, torch.Generator().manual_seed(0))
        torch.save(network.state_dict(), path)
    return path


def accept_fabricated(monkeypatch, module, attribute: str, key: str | None, path: Path) -> None:
    """Make ``module.attribute`` (a WeightsSpec, or a dict of them at ``key``) accept ``path``'s own sha256."""
    from vqtouch.plugins.utils.weights import sha256_of

    prefix = sha256_of(path)[:8]
    specs = getattr(module, attribute)
    if key is None:
        monkeypatch.setattr(module, attribute, dataclasses.replace(specs, sha256_prefix=prefix))
    else:
        monkeypatch.setitem(specs, key, dataclasses.replace(specs[key], sha256_prefix=prefix))


def weighted_metric_options(kind_name: tuple[str, str], folder: Path, monkeypatch) -> dict:
    """Options that give ``("metric", name)`` fabricated weights (an empty dict for metrics without files)."""
    from vqtouch.plugins.evaluation import metrics

    if kind_name == ("metric", "lpips"):
        path = fabricated_torchvision(folder, "vgg16")
        accept_fabricated(monkeypatch, metrics, "LPIPS_TRUNK_WEIGHTS", "vgg", path)
        return {"weights": str(path), "batch_size": 4}
    if kind_name in (("metric", "fid"), ("metric", "kid")):
        return {"weights": str(fabricated_inception(folder))}
    return {}


#: A tiny random open_clip model config (not CLIP, not pretrained): ViT-S-32 layout with 2-layer, 64-wide
#: towers at 64 px, for the clip/text conditioners and the clip_score metric.
TINY_RANDOM_CLIP = {
    "embed_dim": 32,
    "vision_cfg": {"image_size": 64, "layers": 2, "width": 64, "patch_size": 16, "head_width": 32},
    "text_cfg": {"context_length": 77, "vocab_size": 49408, "width": 64, "heads": 2, "layers": 2},
}

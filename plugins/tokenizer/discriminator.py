"""PatchGAN discriminator (Isola et al.), as used by VQGAN: 4x4 convolutions, LeakyReLU 0.2.

GroupNorm replaces BatchNorm: tokenizer batches on a CPU are small, and batch statistics of
4-16 images make the discriminator noisy (taming uses ActNorm for the same reason).
"""

from __future__ import annotations

import torch
from torch import nn

from vqtouch.core import BuildContext, Discriminator

from .discriminator_plugin import PatchGanConfig


class PatchDiscriminator(Discriminator):
    """Maps images (B, C, H, W) in [-1, 1] to a grid of real/fake logits (B, 1, h, w)."""

    def __init__(self, in_channels: int = 3, channels: int = 64, layers: int = 3) -> None:
        super().__init__()
        blocks: list[nn.Module] = [nn.Conv2d(in_channels, channels, 4, stride=2, padding=1), nn.LeakyReLU(0.2)]
        width = channels
        for index in range(1, layers + 1):
            out = channels * min(2**index, 8)
            stride = 2 if index < layers else 1
            blocks += [
                nn.Conv2d(width, out, 4, stride=stride, padding=1, bias=False),
                nn.GroupNorm(min(32, out // 4), out),
                nn.LeakyReLU(0.2),
            ]
            width = out
        blocks.append(nn.Conv2d(width, 1, 4, stride=1, padding=1))
        self.net = nn.Sequential(*blocks)
        for module in self.modules():
            if isinstance(module, nn.Conv2d):
                nn.init.normal_(module.weight, 0.0, 0.02)

    def forward(self, images_BCHW: torch.Tensor) -> torch.Tensor:
        return self.net(images_BCHW)


def hinge_discriminator_loss(logits_real: torch.Tensor, logits_fake: torch.Tensor) -> torch.Tensor:
    """0.5 * (mean relu(1 - D(x)) + mean relu(1 + D(x_hat))), in fp32."""
    return 0.5 * (torch.relu(1 - logits_real.float()).mean() + torch.relu(1 + logits_fake.float()).mean())


def adaptive_weight(
    reconstruction_loss: torch.Tensor, generator_loss: torch.Tensor, last_layer: torch.Tensor, maximum: float = 1e4
) -> torch.Tensor:
    """VQGAN's lambda = ||grad nll|| / (||grad g|| + 1e-4) at the decoder's last layer.

    Computed in fp32, clamped to [0, maximum], detached, and 0 when anything is non-finite (a
    NaN here would otherwise poison every weight through the generator step).
    """
    nll_grad = torch.autograd.grad(reconstruction_loss, last_layer, retain_graph=True)[0].float()
    gan_grad = torch.autograd.grad(generator_loss, last_layer, retain_graph=True)[0].float()
    weight = nll_grad.norm() / (gan_grad.norm() + 1e-4)
    weight = torch.nan_to_num(weight, nan=0.0, posinf=0.0, neginf=0.0).clamp(0.0, maximum)
    return weight.detach()


def build_patchgan(config: PatchGanConfig, context: BuildContext) -> PatchDiscriminator:
    """Factory for ``patchgan``."""
    return PatchDiscriminator(context.channels, config.channels, config.layers)

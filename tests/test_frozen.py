"""vqtouch.plugins.utils.frozen.FrozenModule: a pretrained network held frozen, in eval mode, out of checkpoints."""

import pytest
import torch
from torch import nn

from vqtouch.plugins.utils.frozen import FrozenModule


def pretrained_network() -> nn.Module:
    """A stand-in for a third-party network, with BatchNorm and dropout (train/eval differ)."""
    torch.manual_seed(0)
    network = nn.Sequential(nn.Conv2d(3, 4, 3, padding=1), nn.BatchNorm2d(4), nn.Dropout(0.5), nn.Conv2d(4, 2, 1))
    network.train()
    return network


class Owner(nn.Module):
    """A trainable model using a frozen network, as a conditioner or a perceptual loss does."""

    def __init__(self) -> None:
        super().__init__()
        self.head = nn.Linear(2, 2)
        self.features = FrozenModule(pretrained_network())

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(images).mean(dim=(2, 3)))


def test_weights_stay_out_of_state_dict_and_parameters():
    owner = Owner()
    assert set(owner.state_dict()) == {"head.weight", "head.bias"}
    assert len(list(owner.parameters())) == 2
    assert owner.features.state_dict() == {} and not list(owner.features.parameters())
    # A checkpoint of the owner loads strictly without the frozen weights.
    Owner().load_state_dict(owner.state_dict(), strict=True)


def test_owner_cannot_make_the_network_trainable_or_reinitialise_it():
    owner = Owner()
    before = {key: value.clone() for key, value in owner.features.network.state_dict().items()}
    owner.requires_grad_(True)
    owner.apply(lambda module: nn.init.zeros_(module.weight) if isinstance(module, nn.Conv2d) else None)
    assert not any(p.requires_grad for p in owner.features.network.parameters())
    for key, value in owner.features.network.state_dict().items():
        assert torch.equal(value, before[key]), key


def test_network_stays_in_eval_mode_after_train():
    owner = Owner()
    owner.train()
    assert owner.training and owner.head.training
    assert not owner.features.training
    assert not any(module.training for module in owner.features.network.modules())
    images = torch.rand(2, 3, 8, 8)
    # Eval mode: dropout off and BatchNorm running statistics used, so two calls agree and nothing is updated.
    running_mean = owner.features.network[1].running_mean.clone()
    torch.testing.assert_close(owner(images), owner(images))
    assert torch.equal(owner.features.network[1].running_mean, running_mean)


def test_to_moves_and_casts_the_network():
    owner = Owner()
    assert owner.features.dtype == torch.float32
    owner.to(torch.float64)
    assert owner.features.dtype == torch.float64
    assert all(p.dtype == torch.float64 for p in owner.features.network.parameters())
    assert owner.features.network[1].running_var.dtype == torch.float64
    assert owner(torch.rand(1, 3, 8, 8, dtype=torch.float64)).dtype == torch.float64


def test_gradients_reach_the_inputs_but_not_the_network():
    owner = Owner()
    images = torch.rand(2, 3, 8, 8, requires_grad=True)
    owner(images).sum().backward()
    assert images.grad is not None and images.grad.abs().sum() > 0
    assert all(p.grad is None for p in owner.features.network.parameters())
    assert owner.head.weight.grad is not None


def test_only_modules_are_held():
    with pytest.raises(TypeError, match="holds an nn.Module"):
        FrozenModule(lambda x: x)

"""Holding a frozen pretrained network inside a trainable model, out of its checkpoints.

Components that *use* a third-party pretrained network without training it (a CLIP image
encoder, the ImageNet backbones of perceptual losses and distribution metrics) wrap it in
:class:`FrozenModule`.  The network is held *without* registering it as a submodule, on
purpose:

- checkpoints must not carry megabytes of third-party weights: the network never appears
  in ``state_dict()`` of the wrapper or of any module that owns it, and ``load_state_dict``
  does not expect it (the owner re-loads it from its source when it is rebuilt);
- ``parameters()`` is empty, so no optimizer picks the weights up, and an owner's
  ``requires_grad_(True)`` or ``apply(init_fn)`` cannot reach them;
- ``train()`` is ignored: the network always runs in eval mode (BatchNorm running
  statistics and dropout as at the network's own evaluation time);
- ``_apply`` is forwarded, so an owner's ``.to(device)``, ``.cuda()``, ``.half()``,
  ``.double()`` still move and cast the network with everything else.

Gradients still flow through the network to its *inputs* (what a perceptual loss needs).
The module is model-agnostic: it knows nothing about which network it holds.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn


class FrozenModule(nn.Module):
    """A pretrained network held frozen, in eval mode and out of ``state_dict`` (see module docstring).

    Use it as a child of a trainable model (``self.encoder = FrozenModule(network)``) or
    subclass it to add feature-extraction methods that reach the network through
    :attr:`network`.  Calling the module calls the network.
    """

    def __init__(self, network: nn.Module) -> None:
        """Freeze ``network`` (``requires_grad_(False)``, eval mode) and hold it unregistered."""
        super().__init__()
        if not isinstance(network, nn.Module):
            raise TypeError(f"FrozenModule holds an nn.Module, got {type(network).__name__}")
        network.eval().requires_grad_(False)
        # object.__setattr__ bypasses nn.Module.__setattr__: the network is NOT a submodule, so it stays out of
        # state_dict()/parameters()/children() of this module and of every owner.
        object.__setattr__(self, "_frozen_network", network)
        super().train(False)

    @property
    def network(self) -> nn.Module:
        """The wrapped pretrained network (frozen, eval mode, not a registered submodule)."""
        return self._frozen_network

    @property
    def dtype(self) -> torch.dtype:
        """Floating dtype of the network's weights (inputs are cast to it outside autocast)."""
        for tensor in (*self.network.parameters(), *self.network.buffers()):
            if tensor.is_floating_point():
                return tensor.dtype
        return torch.get_default_dtype()

    def _apply(self, fn: Any, recurse: bool = True) -> FrozenModule:
        # An owner's .to()/.cuda()/.half() reach children through _apply; forward it to the hidden network.
        super()._apply(fn, recurse)
        self._frozen_network._apply(fn)
        return self

    def train(self, mode: bool = True) -> FrozenModule:
        """Ignore ``mode``: a pretrained network always runs as it was evaluated (eval mode)."""
        super().train(False)
        self._frozen_network.eval()
        return self

    def forward(self, *args: Any, **kwargs: Any) -> Any:
        """Call the wrapped network."""
        return self._frozen_network(*args, **kwargs)

    def extra_repr(self) -> str:
        return f"frozen {type(self._frozen_network).__name__}"

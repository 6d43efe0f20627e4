"""What the contract checks share: the default build context, sample keys, tolerances and helpers."""

from __future__ import annotations

import math
import tempfile
from collections.abc import Callable, Iterable, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from torch import nn

from vqtouch.core.components import (
    BuildContext,
    Quantizer,
)
from vqtouch.core.image_size import image_hw

if TYPE_CHECKING:
    pass


#: The context components are built in unless the caller passes one: small images, a few
#: classes, narrow condition tokens and a latent width for quantizers to follow.
DEFAULT_CONTEXT = BuildContext(
    image_size=32, channels=3, num_classes=4, cond_dim=16, latent_dim=8, codebook_size=16, code_grid=4
)

#: The entries of a dataset sample (see :class:`~vqtouch.core.TactileDataset`); ``visual`` is optional.
SAMPLE_KEYS = ("tactile", "label", "text", "sensor", "id")
OPTIONAL_SAMPLE_KEYS = ("visual", "tactile_source")

#: Outputs of a reloaded component must match the saved one to within these tolerances
#: (same weights and inputs on one device: differences are float reassociation at most).
RTOL, ATOL = 1e-5, 1e-6


# -- internals -----------------------------------------------------------------------------------------


def _label(kind: str, name: str) -> str:
    return f"{kind} {name!r}"


def _require(condition: Any, label: str, message: str) -> None:
    if not condition:
        raise AssertionError(f"{label}: {message}")


def _call(label: str, what: str, function: Callable[[], Any]) -> Any:
    """Run ``function``; an exception becomes an AssertionError naming the plugin and the call."""
    try:
        return function()
    except AssertionError:
        raise
    except Exception as exc:  # noqa: BLE001 - any failure of the plugin is a failed contract
        raise AssertionError(f"{label}: {what} raised {type(exc).__name__}: {exc}") from exc


def _skip(reason: str, exc: BaseException) -> None:
    try:
        import pytest
    except ImportError:  # not under pytest: there is nothing to skip, so fail with the cause
        raise exc from None
    pytest.skip(reason)


def _generator(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _images(batch: int, context: BuildContext) -> torch.Tensor:
    return torch.rand(batch, context.channels, *image_hw(context.image_size), generator=_generator(4)) * 2 - 1


def _latents(quantizer: Quantizer) -> torch.Tensor:
    return torch.randn(2, quantizer.embedding_dim, 4, 4, generator=_generator(5))


def _features() -> torch.Tensor:
    centres = torch.tensor([[0.0] * 8, [4.0] * 8, [-4.0] * 8])
    return centres.repeat_interleave(4, dim=0) + 0.1 * torch.randn(12, 8, generator=_generator(6))


def _perturb_(module: nn.Module, seed: int = 7) -> None:
    """Move every floating-point tensor of ``module``'s state off its initial value (in place, seeded):
    parameters by additive noise, buffers (often statistics that must stay positive) by a factor."""
    generator = _generator(seed)
    parameters = {id(p) for p in module.parameters()}
    with torch.no_grad():
        for tensor in module.state_dict(keep_vars=True).values():
            if not tensor.dtype.is_floating_point:
                continue
            noise = torch.randn(tensor.shape, generator=generator).to(tensor.device, tensor.dtype)
            if id(tensor) in parameters:
                tensor.add_(0.05 * noise)
            else:
                tensor.mul_(1 + 0.05 * noise)


def _flatten(value: Any) -> list[Any]:
    if isinstance(value, (tuple, list)):
        return [item for part in value for item in _flatten(part)]
    if isinstance(value, Mapping):
        return [item for key in sorted(value) for item in _flatten(value[key])]
    return [value]


def _assert_same(expected: Any, actual: Any, label: str, message: str) -> None:
    left, right = _flatten(expected), _flatten(actual)
    _require(len(left) == len(right), label, f"{message} (different numbers of outputs)")
    for a, b in zip(left, right):
        if isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor):
            a, b = a.detach().cpu(), b.detach().cpu()
            _require(
                a.shape == b.shape and a.dtype == b.dtype,
                label,
                f"{message}: {a.dtype} {tuple(a.shape)} vs {b.dtype} {tuple(b.shape)}",
            )
            if a.dtype.is_floating_point or a.dtype.is_complex:
                same = torch.allclose(a, b, rtol=RTOL, atol=ATOL, equal_nan=True)
                worst = float((a - b).abs().nan_to_num().max()) if a.numel() else 0.0
                _require(same, label, f"{message} (largest difference {worst:.3g})")
            else:
                _require(torch.equal(a, b), label, message)
        else:
            _require(a == b, label, f"{message}: {a!r} vs {b!r}")


def _close(a: float, b: float) -> bool:
    return math.isclose(a, b, rel_tol=1e-6, abs_tol=1e-9)


@contextmanager
def _folder(tmp_dir: str | Path | None) -> Iterable[str]:
    if tmp_dir is not None:
        Path(tmp_dir).mkdir(parents=True, exist_ok=True)
        yield str(tmp_dir)
        return
    with tempfile.TemporaryDirectory(prefix="vqtouch-check-") as folder:
        yield folder

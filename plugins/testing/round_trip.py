"""The checkpoint round trip every ``nn.Module`` kind passes: saved, reloaded, the same outputs."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from torch import nn

from vqtouch.core import checkpoint
from vqtouch.core.components import (
    Autoencoder,
    BuildContext,
    Clusterer,
    Conditioner,
    Discriminator,
    Generator,
    Quantizer,
    SensorFamily,
)
from vqtouch.core.errors import VqtouchError
from vqtouch.core.image_size import image_hw
from ._support import (
    _assert_same,
    _call,
    _features,
    _folder,
    _generator,
    _images,
    _label,
    _latents,
    _perturb_,
    _require,
)
from .models import _condition_tokens, example_condition, press_height_maps

if TYPE_CHECKING:
    from vqtouch.core.plugin_manager import PluginHost


# -- checkpoint round trip ------------------------------------------------------------------------------


def check_round_trip(
    host: PluginHost,
    component: nn.Module,
    tmp_dir: str | Path | None = None,
    *,
    condition: Any = None,
    step: int = 42,
    label: str | None = None,
) -> nn.Module:
    """Save ``component`` (built by ``host``) and load it back: the reloaded one must be the same.

    Every floating-point tensor of the state is first moved away from its initial value with
    a seeded perturbation, so a reload that fell back to a fresh initialisation cannot pass.
    The reloaded component must have the same type, step, config and context, the same state
    dict (at least one tensor when the module has parameters) and compute the same outputs on
    fixed inputs (what is computed follows the kind's base class; see :func:`probe_outputs`).
    ``component``'s state is perturbed in place.  Returns the reloaded component.
    """
    spec = getattr(component, "vqtouch_spec", None)
    label = label or (_label(spec.kind, spec.config.name) if spec else type(component).__name__)
    _require(spec is not None, label, "was not built through PluginHost.build (no vqtouch_spec)")
    context = spec.context
    if isinstance(component, Clusterer):
        with torch.no_grad():
            _call(label, "fit(features)", lambda: component.fit(_features()))
    _perturb_(component)
    original_state = {key: value.detach().clone() for key, value in component.state_dict().items()}
    has_parameters = any(True for _ in component.parameters())
    _require(
        bool(original_state) or not has_parameters,
        label,
        "has parameters but an empty state_dict: nothing of it would be saved",
    )
    before = probe_outputs(component, context, condition=condition, label=label)
    with _folder(tmp_dir) as folder:
        path = Path(folder) / f"{spec.kind}-{spec.config.name}.safetensors"
        try:
            checkpoint.save(component, path, step=step, host=host)
            restored = checkpoint.load(path, host=host)
        except VqtouchError as exc:
            raise AssertionError(f"{label}: the checkpoint round trip failed: {type(exc).__name__}: {exc}") from exc
    _require(
        type(restored) is type(component),
        label,
        f"reloaded as {type(restored).__name__}, saved as {type(component).__name__}",
    )
    _require(
        getattr(restored, "vqtouch_step", None) == step,
        label,
        f"reloaded step {getattr(restored, 'vqtouch_step', None)!r}, saved step {step}",
    )
    restored_spec = restored.vqtouch_spec
    _require(
        restored_spec.kind == spec.kind and restored_spec.config == spec.config,
        label,
        f"reloaded config {restored_spec.config!r} differs from the saved {spec.config!r}",
    )
    _require(
        restored_spec.context == context,
        label,
        f"reloaded build context {restored_spec.context!r} differs from the saved {context!r}",
    )
    loaded_state = restored.state_dict()
    _require(
        loaded_state.keys() == original_state.keys(),
        label,
        f"reloaded state_dict keys differ: missing {sorted(set(original_state) - set(loaded_state))}, "
        f"unexpected {sorted(set(loaded_state) - set(original_state))}",
    )
    for key, value in original_state.items():
        other = loaded_state[key]
        _require(
            other.dtype == value.dtype and other.shape == value.shape and torch.equal(other.cpu(), value.cpu()),
            label,
            f"tensor {key!r} changed in the checkpoint round trip",
        )
    after = probe_outputs(restored, context, condition=condition, label=label)
    _assert_same(before, after, label, "the reloaded component computes different outputs than the one saved")
    return restored


def probe_outputs(
    component: nn.Module, context: BuildContext, *, condition: Any = None, label: str = "component"
) -> Any:
    """What :func:`check_round_trip` compares before and after the round trip, in eval mode without
    gradients: a sensor's render of fixed presses with a fixed generator; an autoencoder's
    decode(encode(x)) (randomness reset first); a quantizer's output on fixed latents; a
    discriminator's logits; a conditioner's tokens for a fixed condition and its null tokens; a
    clusterer's predictions; a generator's held-out (eval-mode) loss of fixed codes and draws.
    Other modules: None (their state dict is compared)."""
    component.eval()
    with torch.no_grad():
        if isinstance(component, SensorFamily):
            heights = press_height_maps(2, context.image_size, component.field_of_view_mm)
            return _call(label, "render", lambda: component.render(heights, generator=_generator(0)))
        if isinstance(component, Autoencoder):
            images = _images(2, context)
            component.reset_randomness()
            latents = _call(label, "encode", lambda: component.encode(images))
            return latents, _call(label, "decode", lambda: component.decode(latents))
        if isinstance(component, Quantizer):
            out = _call(label, "forward", lambda: component(_latents(component)))
            return out.quantized_BDhw, out.codes_Bhw, out.loss, out.perplexity
        if isinstance(component, Discriminator):
            return _call(label, "forward", lambda: component(_images(2, context)))
        if isinstance(component, Conditioner):
            if condition is None:
                condition = example_condition(component, 3, context)
                _require(
                    condition is not None,
                    label,
                    f"no example condition for sample_key {component.sample_key!r}; pass condition=...",
                )
            tokens = _call(label, "forward", lambda: component(condition))
            return tokens.tokens_BND, component.null(2).tokens_BND
        if isinstance(component, Clusterer):
            return _call(label, "predict", lambda: component.predict(_features()))
        if isinstance(component, Generator):
            codes_BHW = torch.randint(context.codebook_size, (2, *image_hw(context.code_grid)), generator=_generator(1))
            loss, _ = _call(
                label,
                "training_loss",
                lambda: component.training_loss(codes_BHW, _condition_tokens(2, context), generator=_generator(2)),
            )
            return loss
    return None

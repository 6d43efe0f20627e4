"""``vqtouch evaluate tradeoff``'s knobs: what each changes, its values and the baseline's, light so that the
parser can list them (the experiment that measures them is in pipeline_tradeoff.py)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from vqtouch.core import ConfigError, PluginHost
from vqtouch.plugins.utils.seeding import resolve_device
from vqtouch.core.image_size import image_hw, size_text


@dataclass(frozen=True)
class Knob:
    """A knob that costs time: the part of the pipeline it changes, what its values mean, the value
    the baseline has and the values measured when none are given."""

    name: str
    part: str
    meaning: str
    parse: Callable[[str], Any]
    baseline: Callable[[Any, Any], Any]
    alternatives: Callable[[Any, Any, Any], list[Any]]
    #: Tokenizer knobs: set ``value`` in a config dict (``data, value, host``).
    apply: Callable[[dict[str, Any], Any, Any], None] | None = None
    #: Generator knobs: the key of the sampling setting they change.
    setting_key: str | None = None
    show: Callable[[Any], str] = str


def _choice(*options: str) -> Callable[[str], str]:
    def parse(text: str) -> str:
        if text not in options:
            raise ValueError(f"expected {' or '.join(options)}")
        return text

    return parse


def _integer(minimum: int, power_of_two: bool = False) -> Callable[[str], int]:
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise ValueError(f"{text!r} is not an integer") from None
        if value < minimum or (power_of_two and value & (value - 1)):
            raise ValueError(f"expected {'a power of two' if power_of_two else 'an integer'} >= {minimum}")
        return value

    return parse


def _guidance(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{text!r} is not a number") from None
    if not value >= 0 or math.isinf(value):
        raise ValueError("expected a finite guidance scale >= 0 (1: unguided)")
    return value


def _deformable_baseline(config: Any, host: PluginHost) -> str:
    name = config.tokenizer.autoencoder.name if config.tokenizer.autoencoder is not None else None
    if name not in ("dm_vqgan", "vqgan"):
        raise ConfigError(
            f"the deformable knob swaps dm_vqgan and vqgan, but the baseline's autoencoder is {name!r}; "
            "leave it out of --knobs"
        )
    return "on" if name == "dm_vqgan" else "off"


def _set_deformable(data: dict[str, Any], value: str, host: PluginHost) -> None:
    # Keep the options both encoders have (channels, levels, ...): only the deformable parts change.
    name = "dm_vqgan" if value == "on" else "vqgan"
    block = data["tokenizer"]["autoencoder"]
    fields = host.registry("autoencoder").get(name).config_model.model_fields
    data["tokenizer"]["autoencoder"] = {
        "name": name,
        **{key: item for key, item in block.items() if key in fields and key != "name"},
    }


def _codebook_baseline(config: Any, host: PluginHost) -> int:
    size = getattr(config.tokenizer.quantizer, "codebook_size", None)
    if size is None:
        raise ConfigError("the codebook knob needs a quantizer with a codebook_size; leave it out of --knobs")
    return size


def _set(path: str) -> Callable[[dict[str, Any], Any, Any], None]:
    def apply(data: dict[str, Any], value: Any, host: PluginHost) -> None:
        *parents, last = path.split(".")
        node = data
        for part in parents:
            node = node[part]
        node[last] = value

    return apply


def _resolution_alternatives(config: Any, host: PluginHost, baseline: Any) -> list[Any]:
    height, width = image_hw(baseline)
    return [2 * height if height == width else (2 * height, 2 * width)]


def _precision_baseline(config: Any, host: PluginHost) -> str:
    """The tokenizer's training precision in a run of ``config`` (``auto`` resolved)."""
    from vqtouch.plugins.training.precision import (
        resolve_precision,
    )  # imports torch: not when the parser lists the knobs

    return resolve_precision(config.tokenizer.train.precision, resolve_device(config.device), "tokenizer")


def sampling_precision_baseline(config: Any, host: PluginHost | None = None) -> str:
    """The generator's sampling precision in a run of ``config`` (``generator.sample_precision``, ``auto``
    resolved)."""
    from vqtouch.plugins.generator import sampling_precision  # imports torch: not when the parser lists the knobs

    return sampling_precision(config.generator.sample_precision, resolve_device(config.device))


def _downsampling_baseline(config: Any, host: PluginHost) -> int:
    multipliers = getattr(config.tokenizer.autoencoder, "channel_multipliers", None)
    if not multipliers:
        raise ConfigError(
            "the downsampling knob needs an autoencoder with channel_multipliers (vqgan, dm_vqgan); "
            "leave it out of --knobs"
        )
    return 2 ** (len(multipliers) - 1)


def _set_downsampling(data: dict[str, Any], value: int, host: PluginHost) -> None:
    # f = 2^(levels - 1): drop levels, or add levels at the last level's width.
    multipliers = list(data["tokenizer"]["autoencoder"]["channel_multipliers"])
    levels = int(math.log2(value)) + 1
    data["tokenizer"]["autoencoder"]["channel_multipliers"] = multipliers[:levels] + [multipliers[-1]] * max(
        0, levels - len(multipliers)
    )


def _other_samplers(config: Any, host: PluginHost, baseline: str) -> list[str]:
    return [name for name in host.registry("sampler").names() if name != baseline]


KNOBS: dict[str, Knob] = {
    knob.name: knob
    for knob in (
        Knob(
            "deformable",
            "tokenizer",
            "deformable layers on (dm_vqgan) or off (vqgan), the other options kept",
            _choice("on", "off"),
            _deformable_baseline,
            lambda c, h, base: ["off" if base == "on" else "on"],
            apply=_set_deformable,
            show=lambda value: f"{value} ({'dm_vqgan' if value == 'on' else 'vqgan'})",
        ),
        Knob(
            "codebook",
            "tokenizer",
            "codebook size (default: a quarter and 4x the baseline's)",
            _integer(2),
            _codebook_baseline,
            lambda c, h, base: [max(2, base // 4), base * 4],
            apply=_set("tokenizer.quantizer.codebook_size"),
            show=lambda value: f"K = {value}",
        ),
        Knob(
            "resolution",
            "tokenizer",
            "image size in pixels (default: twice the baseline's)",
            _integer(16),
            lambda config, host: config.data.image_size,
            _resolution_alternatives,
            apply=_set("data.image_size"),
            show=lambda value: f"{size_text(value)} px",
        ),
        Knob(
            "precision",
            "tokenizer",
            "training precision, fp32 or bf16 autocast (inference stays fp32, as the stage scores it)",
            _choice("fp32", "bf16"),
            _precision_baseline,
            lambda c, h, base: ["bf16" if base == "fp32" else "fp32"],
            apply=_set("tokenizer.train.precision"),
            show=lambda value: f"train {value}",
        ),
        Knob(
            "downsampling",
            "tokenizer",
            "downsampling factor f of the code grid, a power of two (default: twice the baseline's)",
            _integer(2, power_of_two=True),
            _downsampling_baseline,
            lambda c, h, base: [base * 2],
            apply=_set_downsampling,
            show=lambda value: f"f = {value}",
        ),
        Knob(
            "steps",
            "generator",
            "sampling steps (default: twice and half the configured)",
            _integer(1),
            lambda config, host: config.generator.steps,
            lambda c, h, base: [
                value
                for value in dict.fromkeys([base * 2, max(1, base // 2)])
                if value != base and value <= getattr(c.generator.model, "num_steps", value)
            ],
            setting_key="steps",
            show=lambda value: f"{value} steps",
        ),
        Knob(
            "sampler",
            "generator",
            "sampler plugin (default: every other registered one)",
            str,
            lambda config, host: config.generator.sampler.name,
            _other_samplers,
            setting_key="sampler",
        ),
        Knob(
            "guidance",
            "generator",
            "classifier-free guidance scale (default: 3, or 1 when the baseline is guided)",
            _guidance,
            lambda config, host: config.generator.guidance,
            lambda c, h, base: [3.0 if base == 1 else 1.0],
            setting_key="guidance",
            show=lambda value: f"g = {value:g}",
        ),
        Knob(
            "sampling-precision",
            "generator",
            "precision of the generator's network while sampling, fp32 or bf16 autocast",
            _choice("fp32", "bf16"),
            sampling_precision_baseline,
            lambda c, h, base: ["bf16" if base == "fp32" else "fp32"],
            setting_key="precision",
        ),
    )
}


def known_knobs() -> str:
    """The knob names, for error messages and help."""
    return ", ".join(KNOBS)

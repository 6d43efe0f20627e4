"""The configs ``vqtouch evaluate tradeoff`` measures (:mod:`vqtouch.plugins.experiments.pipeline_tradeoff`):
the knobs asked for, the scene's config scaled and shortened into the baseline, and one variant per seed
and knob value."""

from __future__ import annotations

import copy
from typing import Any

from vqtouch.core import ConfigError, PluginHost, validate_experiment
from vqtouch.core.config import scale_for_demo

from .pipeline_tradeoff_knobs import KNOBS, known_knobs, sampling_precision_baseline

#: The scene whose baseline the command measures when none is named: a tokenizer and a generator.
DEFAULT_SCENE = "label-to-touch"


def parse_knobs(specs: list[str] | None, config: Any, host: PluginHost) -> dict[str, list[Any]]:
    """The knobs to measure and their values, from ``--knobs NAME[=V1,V2,...] ...`` (None: every
    knob of the parts the baseline trains, at its default values).  One-line errors for an unknown
    knob (listing the known ones), a value that does not parse, a knob given twice and a value that
    is the baseline's own (the baseline is always measured)."""
    has_generator = "generator" in config.stages
    if specs is None:
        specs = [name for name, knob in KNOBS.items() if knob.part == "tokenizer" or has_generator]
    chosen: dict[str, list[Any]] = {}
    for spec in specs:
        name, separator, text = spec.partition("=")
        name = name.strip()
        if name not in KNOBS:
            raise ConfigError(f"--knobs {spec}: unknown knob {name!r}; known knobs: {known_knobs()}")
        if name in chosen:
            raise ConfigError(
                f"--knobs {spec}: the knob {name!r} is given twice; give its values once, e.g. {name}=A,B"
            )
        knob = KNOBS[name]
        if knob.part == "generator" and not has_generator:
            raise ConfigError(
                f"--knobs {spec}: the {name} knob is a generator knob, but the scene "
                f"{config.scene!r} trains no generator; use e.g. --scene {DEFAULT_SCENE}"
            )
        baseline = knob.baseline(config, host)
        if separator:
            values = []
            for item in text.split(","):
                try:
                    values.append(knob.parse(item.strip()))
                except ValueError as exc:
                    raise ConfigError(f"--knobs {spec}: {item.strip()!r}: {exc} ({knob.meaning})") from None
            if baseline in values:
                raise ConfigError(
                    f"--knobs {spec}: {knob.show(baseline)} is the baseline's own value, measured "
                    "anyway; give other values"
                )
        else:
            values = knob.alternatives(config, host, baseline)
        chosen[name] = list(dict.fromkeys(values))
    return chosen


def scaled_config(config: Any, host: PluginHost, full: bool) -> Any:
    """``config`` scaled down like ``vqtouch demo`` (unless ``full``): the sizes the knobs' default
    values and the baseline derive from."""

    if "tokenizer" not in config.stages:
        raise ConfigError(f"the scene {config.scene!r} trains no tokenizer; use e.g. --scene {DEFAULT_SCENE}")
    if config.data.val_fraction == 0:
        raise ConfigError(
            "data.val_fraction=0 holds no images out: nothing to score the settings on; set data.val_fraction=0.1"
        )
    return config if full else scale_for_demo(config, host)


def baseline_config(
    config: Any, host: PluginHost, *, tokenizer_steps: int, generator_steps: int, generator: bool
) -> Any:
    """The baseline: ``config`` (see :func:`scaled_config`) with the tokenizer (and with
    ``generator`` the generator) trained for the given steps, one checkpoint at the end, and only
    the stages the experiment runs.  The generator stage scores no samples itself: the experiment
    scores every setting."""
    data = config.to_dict()
    stages = {"tokenizer": tokenizer_steps, **({"generator": generator_steps} if generator else {})}
    for stage, steps in stages.items():
        train = data[stage]["train"]
        train |= {"steps": steps, "checkpoint_every": steps, "log_every": min(train["log_every"], steps)}
    if generator:
        data["generator"]["num_samples"] = 0
    data["stages"] = list(stages)
    return validate_experiment(data, host)


def variant_config(baseline: Any, host: PluginHost, seed: int, knob: str | None = None, value: Any = None) -> Any:
    """The baseline at ``seed`` (initialisation, data order and held-out split), with ``knob`` set
    to ``value`` (a tokenizer knob: the variant trains the tokenizer only)."""
    data = copy.deepcopy(baseline.to_dict()) | {"seed": seed}
    if knob is not None:
        KNOBS[knob].apply(data, value, host)
        data["stages"] = ["tokenizer"]
    try:
        return validate_experiment(data, host)
    except ConfigError as exc:
        raise ConfigError(f"--knobs {knob}={value}: {exc}") from None


def baseline_text(config: Any, host: PluginHost) -> str:
    """The baseline tokenizer's value of every tokenizer knob, e.g. ``on (dm_vqgan), K = 512, 64 px``."""
    shown = []
    for knob in KNOBS.values():
        if knob.part == "tokenizer":
            try:
                shown.append(knob.show(knob.baseline(config, host)))
            except ConfigError:
                continue
    return ", ".join(shown)


def check_sampling_values(config: Any, host: PluginHost, knobs: dict[str, list[Any]]) -> None:
    """One-line errors for a sampler that is not registered and for more sampling steps than the
    generator's diffusion steps, before anything trains."""
    for name in knobs.get("sampler", []):
        host.registry("sampler").get(name)  # its error lists the registered samplers
    limit = getattr(config.generator.model, "num_steps", None) if "steps" in knobs else None
    too_many = [value for value in knobs.get("steps", []) if limit and value > limit]
    if too_many:
        raise ConfigError(
            f"--knobs steps={too_many[0]}: more sampling steps than the generator's {limit} diffusion "
            f"steps (generator.model.num_steps); give at most {limit}"
        )


def generator_base(config: Any) -> dict[str, Any]:
    """The configured sampling setting (the generator part's baseline)."""
    section = config.generator
    return {
        "sampler": section.sampler.name,
        "steps": section.steps,
        "guidance": section.guidance,
        "precision": sampling_precision_baseline(config),
    }

"""The entry point of the contract checks and the registration contract every kind shares."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from pydantic import ValidationError
from torch import nn

from vqtouch.core.components import (
    Autoencoder,
    BestOfRanker,
    BuildContext,
    Clusterer,
    Conditioner,
    Discriminator,
    Generator,
    Metric,
    Quantizer,
    Sampler,
    SensorFamily,
    TactileDataset,
)
from vqtouch.core.errors import MissingWeightsError, VqtouchError
from vqtouch.core.plugin_config import PluginConfig, literal_name_of

from ._support import DEFAULT_CONTEXT, _label, _require, _skip
from .round_trip import check_round_trip
from .data import check_clusterer, check_dataset, check_metric
from .rankers import check_best_of_ranker
from .models import (
    _check_sampler_with_host,
    check_autoencoder,
    check_conditioner,
    check_discriminator,
    check_generator,
    check_quantizer,
    check_sensor_family,
)

if TYPE_CHECKING:
    from vqtouch.core.plugin_manager import PluginHost


# -- the entry point ---------------------------------------------------------------------------------


def check_plugin(
    host: PluginHost,
    kind: str,
    name: str,
    options: Mapping[str, Any] | None = None,
    context: BuildContext | None = None,
    *,
    inputs: Mapping[str, Any] | None = None,
    condition: Any = None,
    tmp_dir: str | Path | None = None,
    missing_weights: Literal["skip", "raise"] = "skip",
) -> Any:
    """Run every contract check of ``kind`` on the plugin registered as ``name``; returns the built component
    (for ``kind="stage"``: the stage's entry, see :func:`check_stage`).

    ``options``: the plugin's options besides ``name`` (keep them small: the checks build and
    run the component several times).  ``context``: the :class:`BuildContext` to build in
    (default :data:`DEFAULT_CONTEXT`).  ``inputs``: built components the plugin declared with
    ``register(..., inputs=(...))``, e.g. ``{"sensor": sensor}`` for a dataset that renders.
    ``condition``: a batch of raw conditions for a conditioner whose ``sample_key`` has no
    default example (see :func:`example_condition`).  ``tmp_dir``: where the round-trip
    checkpoint is written (default: a temporary folder).  ``missing_weights``: what to do when
    the build needs a pretrained file that is not present: ``"skip"`` the test (under pytest)
    or ``"raise"`` the :class:`~vqtouch.core.MissingWeightsError`.

    A dataset's samples must have the context's image size unless ``options`` set ``image_size``.
    The returned component has been through :func:`check_round_trip`, so its weights were
    perturbed in place.  Raises AssertionError naming the plugin and the broken rule on the first
    failed check.
    """
    if kind == "stage":
        return check_stage(host, name)
    context = context or DEFAULT_CONTEXT
    check_registration(host, kind, name)
    component = build_for_check(host, kind, name, options, context, inputs=inputs, missing_weights=missing_weights)
    label = _label(kind, name)
    base = host.registry(kind).base_type
    for base_class, check in _BEHAVIOUR_CHECKS:
        if base is not None and issubclass(base, base_class):
            check(
                component,
                context,
                label=label,
                condition=condition,
                host=host,
                image_size=None if "image_size" in (options or {}) else context.image_size,
            )
    if base is not None and issubclass(base, nn.Module):
        check_round_trip(host, component, tmp_dir, condition=condition, label=label)
    return component


def check_stage(host: PluginHost, name: str) -> Any:
    """The contract of a registered stage (``check_plugin(host, "stage", name)``); returns its entry.

    ``run`` is a callable of one argument (the :class:`~vqtouch.core.StageJob`); the stage has a
    description; its section, if it has one, is a :class:`~vqtouch.core.Section` that is strict,
    documented (a docstring and a description on every field) and valid with its defaults; its
    ``demo`` caps name options of its section; every slot it needs or uses exists.
    """
    import inspect

    from vqtouch.core.config import Section

    label = f"stage {name!r}"
    try:
        stage = host.stage(name)
    except VqtouchError as exc:
        raise AssertionError(f"{label} is not registered: {exc}") from exc
    _require(callable(stage.load_run()), label, "run is not callable")
    try:
        parameters = [
            p
            for p in inspect.signature(stage.load_run()).parameters.values()
            if p.default is inspect.Parameter.empty and p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)
        ]
    except (TypeError, ValueError):
        parameters = [None]
    _require(len(parameters) == 1, label, f"run must take one argument, the StageJob (it requires {len(parameters)})")
    _require(
        bool(stage.description.strip()),
        label,
        "no description (it is the stage's documentation in `vqtouch config stages`)",
    )
    missing = [path for path in stage.slots if path not in host.slots]
    _require(not missing, label, f"declares slots the experiment config does not have: {missing}")
    section = stage.section
    if section is None:
        _require(not stage.demo, label, f"demo caps {sorted(stage.demo)} but the stage has no section")
        return stage
    _require(
        isinstance(section, type) and issubclass(section, Section),
        label,
        f"section {section!r} is not a vqtouch.core.Section subclass",
    )
    _require(section.model_config.get("extra") == "forbid", label, f"section {section.__name__} accepts unknown keys")
    _require(bool(section.__doc__ and section.__doc__.strip()), label, f"section {section.__name__} has no docstring")
    undocumented = [field for field, info in section.model_fields.items() if not info.description]
    _require(not undocumented, label, f"section {section.__name__} fields without description: {undocumented}")
    try:
        section.model_validate({}, context={"host": host})
    except ValidationError as exc:
        raise AssertionError(
            f"{label}: section {section.__name__} is not valid with its defaults: {exc.errors()[0]['msg']}"
        ) from exc
    unknown = [key for key in stage.demo if key.split(".")[0] not in section.model_fields]
    _require(not unknown, label, f"demo caps name options its section does not have: {unknown}")
    return stage


def build_for_check(
    host: PluginHost,
    kind: str,
    name: str,
    options: Mapping[str, Any] | None = None,
    context: BuildContext | None = None,
    *,
    inputs: Mapping[str, Any] | None = None,
    missing_weights: Literal["skip", "raise"] = "skip",
) -> Any:
    """Build ``name`` of ``kind`` through ``host`` and check it is an instance of the kind's base class.

    A build error is an AssertionError (the options given are assumed valid); a missing
    pretrained file skips the test or raises, as ``missing_weights`` says (see :func:`check_plugin`).
    """
    label = _label(kind, name)
    registry = host.registry(kind)
    entry = registry.get(name)
    inputs = dict(inputs or {})
    missing = [item for item in entry.inputs if inputs.get(item) is None]
    _require(
        not missing,
        label,
        f"declares inputs {list(entry.inputs)}; pass the built components with "
        f"inputs={{{', '.join(repr(m) + ': ...' for m in missing)}}}",
    )
    try:
        component = host.build(kind, {**dict(options or {}), "name": name}, context or DEFAULT_CONTEXT, **inputs)
    except MissingWeightsError as exc:
        if missing_weights == "raise":
            raise
        _skip(f"{label} needs a pretrained file that is not present: {exc}", exc)
    except Exception as exc:  # noqa: BLE001 - a user error (VqtouchError) or a bug in the factory alike
        raise AssertionError(
            f"{label}: building it with options {dict(options or {})} failed: {type(exc).__name__}: {exc}"
        ) from exc
    base = registry.base_type
    _require(
        base is None or isinstance(component, base),
        label,
        f"built a {type(component).__name__}, which is not a vqtouch.core.{getattr(base, '__name__', '?')}",
    )
    spec = getattr(component, "vqtouch_spec", None)
    _require(
        spec is not None and spec.kind == kind and spec.config.name == name,
        label,
        "the built component does not carry the vqtouch_spec the host attaches (kind, config, context)",
    )
    return component


# -- registration ------------------------------------------------------------------------------------


def check_registration(host: PluginHost, kind: str, name: str) -> Any:
    """The registration contract of one entry; returns the entry.

    The options model is a :class:`~vqtouch.core.PluginConfig`, strict (unknown keys fail) and
    frozen, documented (a docstring and a description on every field), declares
    ``name: Literal[<name>]`` and has a default for every option, so selecting the plugin by
    name alone works.  The entry has a description, and its ``demo`` caps name top-level
    options with numeric caps.
    """
    label = _label(kind, name)
    try:
        entry = host.registry(kind).get(name)
    except VqtouchError as exc:
        raise AssertionError(f"{label} is not registered: {exc}") from exc
    _require(entry.name == name, label, f"{name!r} is an alias of {entry.name!r}; check the canonical name")
    model = entry.config_model
    _require(
        isinstance(model, type) and issubclass(model, PluginConfig),
        label,
        f"config {model!r} is not a vqtouch.core.PluginConfig subclass",
    )
    _require(
        model.model_config.get("extra") == "forbid",
        label,
        f"config {model.__name__} accepts unknown keys (model_config extra={model.model_config.get('extra')!r}); "
        "subclass vqtouch.core.PluginConfig without loosening extra",
    )
    _require(model.model_config.get("frozen") is True, label, f"config {model.__name__} is not frozen")
    _require(
        bool(model.__doc__ and model.__doc__.strip()),
        label,
        f"config {model.__name__} has no docstring (it is the plugin's documentation in `vqtouch config`)",
    )
    undocumented = [field for field, info in model.model_fields.items() if not info.description]
    _require(not undocumented, label, f"config {model.__name__} fields without description: {undocumented}")
    declared = literal_name_of(model)
    _require(
        declared == name,
        label,
        f"config {model.__name__} declares name {declared!r}; it must declare `name: Literal[{name!r}] = {name!r}`",
    )
    try:
        default = model()
    except ValidationError as exc:
        raise AssertionError(
            f"{label}: config {model.__name__} has options without a default, so "
            f"`--set <slot>.name={name}` alone cannot select it: {exc}"
        ) from exc
    _require(default.name == name, label, f"config {model.__name__}() has name {default.name!r}, not {name!r}")
    try:
        model.model_validate({"name": name, "no_such_option_for_the_contract_check": 1})
    except ValidationError:
        pass
    else:
        raise AssertionError(f"{label}: config {model.__name__} accepted an unknown option; it must be strict")
    _require(
        bool(entry.description and entry.description.strip()),
        label,
        "registered without a description (register(..., description=...))",
    )
    for path, cap in entry.demo.items():
        _require(
            str(path).split(".")[0] in model.model_fields,
            label,
            f"demo cap {path!r} names no option of {model.__name__} (options: {', '.join(model.model_fields)})",
        )
        _require(
            isinstance(cap, (int, float)) and not isinstance(cap, bool),
            label,
            f"demo cap {path!r} = {cap!r} is not a number",
        )
    for item in entry.inputs:
        _require(isinstance(item, str) and item.isidentifier(), label, f"input {item!r} is not a keyword name")
    return entry


#: The behaviour check of each base class, called as ``check(component, context, label=..., condition=...,
#: image_size=...)`` (condition: for conditioners; image_size: the S a dataset's samples must have).
_BEHAVIOUR_CHECKS: tuple[tuple[type, Callable[..., None]], ...] = (
    (SensorFamily, lambda c, ctx, label, **_: check_sensor_family(c, ctx, label=label)),
    (Conditioner, lambda c, ctx, label, condition, **_: check_conditioner(c, ctx, condition=condition, label=label)),
    (Autoencoder, lambda c, ctx, label, **_: check_autoencoder(c, ctx, label=label)),
    (Quantizer, lambda c, ctx, label, **_: check_quantizer(c, ctx, label=label)),
    (Discriminator, lambda c, ctx, label, **_: check_discriminator(c, ctx, label=label)),
    (Clusterer, lambda c, ctx, label, **_: check_clusterer(c, ctx, label=label)),
    (Metric, lambda c, ctx, label, **_: check_metric(c, ctx, label=label)),
    (TactileDataset, lambda c, ctx, label, image_size, **_: check_dataset(c, image_size, label=label)),
    (Generator, lambda c, ctx, label, **_: check_generator(c, ctx, label=label)),
    (Sampler, lambda c, ctx, label, host, **_: _check_sampler_with_host(c, ctx, label=label, host=host)),
    (BestOfRanker, lambda c, ctx, label, **_: check_best_of_ranker(c, ctx, label=label)),
)

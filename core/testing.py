"""Contract checks for plugin authors: the checks every built-in plugin passes, for your own.

Call :func:`check_plugin` from your package's pytest suite to check one registered plugin
against the contract of its kind, exactly as vqtouch's own test suite checks the built-ins::

    from vqtouch.core import load_plugins
    from vqtouch.core.testing import check_plugin

    def test_my_sensor_meets_the_vqtouch_contract(tmp_path):
        host = load_plugins(autoload=False, extra=["my_package.vqtouch_plugin"])
        check_plugin(host, "sensor_family", "my_sensor", tmp_dir=tmp_path)

    def test_my_conditioner_meets_the_vqtouch_contract(tmp_path):
        host = load_plugins(autoload=False, extra=["my_package.vqtouch_plugin"])
        check_plugin(host, "conditioner", "my_conditioner", options={"width": 8}, tmp_dir=tmp_path)

A failed check raises :class:`AssertionError` whose message names the plugin and what is
wrong, so pytest reports it like any failed ``assert``.  What is checked:

- for every kind, the registration contract (:func:`check_registration`): a strict, frozen,
  documented options model whose ``name`` is ``Literal[<registered name>]`` and whose options
  all have defaults, a description, ``demo`` caps that name real options;
- the component is built from ``options`` (tiny ones keep the checks fast) in ``context`` and
  is an instance of its kind's base class from :mod:`vqtouch.core.components`;
- the behaviour of that base class: :func:`check_sensor_family`, :func:`check_conditioner`,
  :func:`check_autoencoder`, :func:`check_quantizer`, :func:`check_discriminator`,
  :func:`check_clusterer`, :func:`check_metric`, :func:`check_dataset`, :func:`check_generator`,
  :func:`check_sampler`;
- for every ``nn.Module`` kind, the checkpoint round trip (:func:`check_round_trip`): saved
  with :func:`vqtouch.core.save` and rebuilt with :func:`vqtouch.core.load`, the component
  has the same state and computes the same outputs on fixed inputs.

The checks dispatch on the kind's base class, never on plugin names.  A plugin whose build
needs a pretrained file that is not present (:class:`~vqtouch.core.MissingWeightsError`) is
skipped under pytest with the error's message, which names the file; pass
``missing_weights="raise"`` to fail instead.  Each ``check_*`` function can also be called
on its own with a component you built.
"""

from __future__ import annotations

import math
import tempfile
from collections.abc import Callable, Iterable, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import torch
from pydantic import ValidationError
from torch import nn

from . import checkpoint
from .components import (
    Autoencoder,
    BuildContext,
    Clusterer,
    Conditioner,
    ConditionTokens,
    Discriminator,
    Generator,
    Metric,
    Quantizer,
    QuantizerOutput,
    Sampler,
    SensorFamily,
    TactileDataset,
)
from .errors import MissingWeightsError, VqtouchError
from .image_size import ImageSize, image_hw, pixel_centres_mm, size_text
from .plugin_config import PluginConfig, literal_name_of

if TYPE_CHECKING:
    from .plugin_manager import PluginHost


__all__ = [
    "DEFAULT_CONTEXT",
    "SAMPLE_KEYS",
    "build_for_check",
    "check_autoencoder",
    "check_clusterer",
    "check_conditioner",
    "check_dataset",
    "check_discriminator",
    "check_generator",
    "check_metric",
    "check_plugin",
    "check_quantizer",
    "check_registration",
    "check_sampler",
    "schedule_from_host",
    "check_round_trip",
    "check_sensor_family",
    "example_condition",
    "press_height_maps",
    "probe_outputs",
]

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

    from .config import Section

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


# -- behaviour of each base class ----------------------------------------------------------------------


def press_height_maps(batch: int, size: ImageSize, field_of_view_mm: float, depth_mm: float = 1.0) -> torch.Tensor:
    """(batch, H, W) indentations in mm (``size`` S or (H, W)): a sphere pressed ``depth_mm`` deep, a
    little off-centre and a little deeper in each row, drawn at the physical scale of
    ``field_of_view_mm`` (the side of the square it covers, with square pixels along the shorter side)."""
    height, width = image_hw(size)
    ys, xs = pixel_centres_mm(
        height, width, tuple(field_of_view_mm * side / min(height, width) for side in (height, width))
    )
    radius = field_of_view_mm / 4
    maps = []
    for row in range(batch):
        shift = field_of_view_mm * 0.05 * row
        depth = depth_mm * (1 + 0.25 * row)
        cap = (radius**2 - (xs - shift) ** 2 - (ys + shift / 2) ** 2).clamp_min(0).sqrt() - (radius - depth)
        maps.append(cap.clamp_min(0))
    return torch.stack(maps)


def check_sensor_family(sensor: SensorFamily, context: BuildContext | None = None, *, label: str = "sensor") -> None:
    """A sensor family renders (B, H, W) mm height maps to finite (B, 3, H, W) images in [0, 1],
    deterministically for a fixed generator, shows a contact, stays finite at extremes (flat, a deep
    sharp-edged press) and declares a sensible field of view, sensor id and reference frames."""
    context = context or DEFAULT_CONTEXT
    height, width = image_hw(context.image_size)
    fov = sensor.field_of_view_mm
    _require(
        isinstance(fov, (int, float)) and math.isfinite(fov) and fov > 0,
        label,
        f"field_of_view_mm must be a positive number of mm, got {fov!r}",
    )
    _require(isinstance(sensor.sensor_id, str), label, f"sensor_id must be a str, got {sensor.sensor_id!r}")
    sensor.eval()
    press = press_height_maps(2, context.image_size, fov)
    flat = torch.zeros(2, height, width)
    deep = torch.zeros(2, height, width)
    deep[:, height // 4 : 3 * height // 4, width // 4 : 3 * width // 4] = 50.0
    with torch.no_grad():
        rendered = {
            what: _call(
                label, f"render({what} height maps)", lambda h=heights: sensor.render(h, generator=_generator(0))
            )
            for what, heights in (("pressed", press), ("flat", flat), ("deep", deep))
        }
        again = _call(label, "render(pressed) again", lambda: sensor.render(press, generator=_generator(0)))
    for what, images in rendered.items():
        _require(
            isinstance(images, torch.Tensor), label, f"render({what}) returned {type(images).__name__}, not a tensor"
        )
        _require(
            tuple(images.shape) == (2, 3, height, width),
            label,
            f"render of (2, {height}, {width}) {what} height maps returned shape {tuple(images.shape)}; "
            f"expected (2, 3, {height}, {width})",
        )
        _require(images.dtype.is_floating_point, label, f"render({what}) returned dtype {images.dtype}")
        _require(bool(torch.isfinite(images).all()), label, f"render({what}) has NaN or Inf values")
        low, high = float(images.min()), float(images.max())
        _require(
            low >= 0.0 and high <= 1.0,
            label,
            f"render({what}) has values outside [0, 1] (min {low:.4g}, max {high:.4g})",
        )
    _require(
        torch.equal(rendered["pressed"], again),
        label,
        "render is not deterministic for a fixed generator: two calls with "
        "torch.Generator().manual_seed(0) gave different images (draw noise from `generator`)",
    )
    _require(
        float((rendered["pressed"] - rendered["flat"]).abs().max()) > 1e-3,
        label,
        "a 1 mm press renders the same image as no contact: the height map does not reach the image",
    )
    frames = _call(label, f"reference_frames({height}, {width})", lambda: sensor.reference_frames(height, width))
    if frames is not None:
        _require(
            isinstance(frames, torch.Tensor) and frames.ndim == 4 and tuple(frames.shape[1:]) == (3, height, width),
            label,
            f"reference_frames({height}, {width}) must be None or (N, 3, {height}, {width}), got "
            f"{tuple(getattr(frames, 'shape', ()))}",
        )
        _require(
            bool(torch.isfinite(frames).all()) and float(frames.min()) >= 0 and float(frames.max()) <= 1,
            label,
            "reference_frames has values outside [0, 1] or non-finite values",
        )
    extent = _call(label, f"imaged_extent_mm({height}, {width})", lambda: sensor.imaged_extent_mm(height, width))
    _require(
        isinstance(extent, tuple)
        and len(extent) == 2
        and all(isinstance(side, (int, float)) and math.isfinite(side) and side > 0 for side in extent),
        label,
        f"imaged_extent_mm({height}, {width}) must be a (rows, columns) pair of positive mm, got {extent!r}",
    )


def example_condition(conditioner: Conditioner, batch: int, context: BuildContext | None = None) -> Any:
    """A fixed batch of raw conditions for ``conditioner``, chosen from its ``sample_key`` the way a
    collated dataset batch holds them: ``label`` integer labels (B,) below the context's class
    count, ``tactile``/``tactile_source``/``visual`` images (B, channels, H, W) in [0, 1], ``text`` a
    list of B strings.
    Returns None for any other key (pass ``condition=`` to the checks then)."""
    context = context or DEFAULT_CONTEXT
    key = conditioner.sample_key
    if key == "label":
        return torch.arange(batch) % max(context.num_classes, 1)
    if key in ("tactile", "tactile_source", "visual"):
        channels = context.channels if key.startswith("tactile") else 3
        return torch.rand(batch, channels, *image_hw(context.image_size), generator=_generator(1))
    if key == "text":
        texts = ["a smooth sphere pressed into the gel", "a coarse woven fabric", "a sharp metal edge"]
        return [texts[i % len(texts)] for i in range(batch)]
    if key == "sensor_index":  # a sensor tag's rows: which sensor each is
        return torch.arange(batch) % max(int(getattr(conditioner, "num_sensors", 1)), 1)
    return None


def check_conditioner(
    conditioner: Conditioner, context: BuildContext | None = None, *, condition: Any = None, label: str = "conditioner"
) -> None:
    """A conditioner reads a documented sample key and turns a batch of conditions into finite tokens
    (B, num_tokens, cond_dim) with cond_dim the context's; rows of the drop mask get exactly the
    learned null tokens and the other rows are unchanged; ``null(B)`` is the null tokens, flagged."""
    context = context or DEFAULT_CONTEXT
    key = conditioner.sample_key
    _require(
        isinstance(key, str) and key not in ("", "sensor", "id"),
        label,
        f"sample_key {key!r} is not a condition: name the sample entry it reads (label, tactile, "
        "tactile_source, visual, text, or another a dataset provides) or the condition it derives",
    )
    _require(
        conditioner.cond_dim == context.cond_dim,
        label,
        f"emits tokens of width {conditioner.cond_dim}, but the context asks for cond_dim={context.cond_dim}",
    )
    _require(
        isinstance(conditioner.num_tokens, int) and conditioner.num_tokens >= 1,
        label,
        f"num_tokens must be a positive int, got {conditioner.num_tokens!r}",
    )
    batch = 3
    if condition is None:
        condition = example_condition(conditioner, batch, context)
        _require(
            condition is not None,
            label,
            f"no example condition for sample_key {key!r}; pass condition=<a batch of {batch}>",
        )
    else:
        batch = len(condition)
    _require(
        conditioner.condition_of({key: condition, "id": ["x"] * batch}) is condition,
        label,
        f"condition_of(batch) must return batch[{key!r}]",
    )
    conditioner.eval()
    shape = (batch, conditioner.num_tokens, context.cond_dim)
    with torch.no_grad():
        out = _call(label, "forward(condition)", lambda: conditioner(condition))
        drop_B = torch.zeros(batch, dtype=torch.bool)
        drop_B[0] = True
        dropped = _call(label, "forward(condition, drop_mask)", lambda: conditioner(condition, drop_B))
        null = _call(label, f"null({batch})", lambda: conditioner.null(batch))
    for what, tokens in (("forward", out), ("forward with a drop mask", dropped), ("null", null)):
        _require(
            isinstance(tokens, ConditionTokens), label, f"{what} returned {type(tokens).__name__}, not ConditionTokens"
        )
        _require(
            tuple(tokens.tokens_BND.shape) == shape,
            label,
            f"{what} returned tokens of shape {tuple(tokens.tokens_BND.shape)}; expected {shape}",
        )
        _require(bool(torch.isfinite(tokens.tokens_BND).all()), label, f"{what} returned NaN or Inf tokens")
        _require(
            tokens.is_null_B.dtype == torch.bool and tuple(tokens.is_null_B.shape) == (batch,),
            label,
            f"{what} returned is_null_B of dtype {tokens.is_null_B.dtype} and shape "
            f"{tuple(tokens.is_null_B.shape)}; expected bool ({batch},)",
        )
    null_ND = conditioner.null_tokens_ND.detach()
    _require(not bool(out.is_null_B.any()), label, "forward without a drop mask flagged rows as null")
    _require(
        torch.equal(dropped.is_null_B, drop_B),
        label,
        "forward(condition, drop_mask) must flag exactly the dropped rows in is_null_B",
    )
    _require(
        torch.equal(dropped.tokens_BND[0], null_ND.to(dropped.tokens_BND.dtype)),
        label,
        "a dropped row does not carry the learned null tokens (null_tokens_ND)",
    )
    _require(
        torch.equal(dropped.tokens_BND[1:], out.tokens_BND[1:]),
        label,
        "dropping row 0 changed the tokens of the rows that were not dropped",
    )
    _require(
        bool(null.is_null_B.all()) and all(torch.equal(row, null_ND) for row in null.tokens_BND),
        label,
        "null(B) must return the learned null tokens for every row, all flagged in is_null_B",
    )
    single = example_condition(conditioner, 1, context)
    if single is not None:  # batch 1 (a single condition at generation time) must work too
        with torch.no_grad():
            one = _call(label, "forward(condition of batch 1)", lambda: conditioner(single))
        _require(
            tuple(one.tokens_BND.shape) == (1, *shape[1:]) and bool(torch.isfinite(one.tokens_BND).all()),
            label,
            f"a batch of 1 gave tokens of shape {tuple(one.tokens_BND.shape)} (or non-finite ones)",
        )


def check_autoencoder(
    autoencoder: Autoencoder, context: BuildContext | None = None, *, label: str = "autoencoder"
) -> None:
    """An autoencoder maps images (B, C, H, W) in [-1, 1] to finite latents (B, latent_channels, H/f, W/f)
    and back to (B, C, H, W); decode is a pure function of its input, ``reset_randomness`` makes an
    evaluation repeat exactly and ``context_facts`` reports the latent width."""
    context = context or DEFAULT_CONTEXT
    factor, width = autoencoder.downsample_factor, autoencoder.latent_channels
    (rows, cols), size = image_hw(context.image_size), size_text(context.image_size)
    _require(
        isinstance(factor, int) and factor >= 1 and rows % factor == 0 and cols % factor == 0,
        label,
        f"downsample_factor {factor!r} must be a positive int dividing the image size {size}",
    )
    _require(isinstance(width, int) and width >= 1, label, f"latent_channels must be a positive int, got {width!r}")
    _require(
        autoencoder.context_facts().get("latent_dim") == width,
        label,
        f"context_facts() must report latent_dim={width} (its latent_channels) for the quantizer",
    )
    images = _images(2, context)
    autoencoder.eval()
    with torch.no_grad():
        autoencoder.reset_randomness()
        latents = _call(label, "encode(images)", lambda: autoencoder.encode(images))
        _require(
            tuple(latents.shape) == (2, width, rows // factor, cols // factor),
            label,
            f"encode of (2, {context.channels}, {rows}, {cols}) returned {tuple(latents.shape)}; expected "
            f"(2, {width}, {rows // factor}, {cols // factor})",
        )
        _require(bool(torch.isfinite(latents).all()), label, "encode returned NaN or Inf latents")
        decoded = _call(label, "decode(latents)", lambda: autoencoder.decode(latents))
        _require(
            tuple(decoded.shape) == tuple(images.shape),
            label,
            f"decode returned {tuple(decoded.shape)}; expected {tuple(images.shape)}",
        )
        _require(bool(torch.isfinite(decoded).all()), label, "decode returned NaN or Inf images")
        _assert_same(
            decoded,
            _call(label, "decode(latents) again", lambda: autoencoder.decode(latents)),
            label,
            "decode is not a pure function of its input (two calls on the same latents differ)",
        )
        autoencoder.reset_randomness()
        repeated = _call(label, "encode after reset_randomness", lambda: autoencoder.decode(autoencoder.encode(images)))
        _assert_same(
            decoded,
            repeated,
            label,
            "decode(encode(x)) differs after reset_randomness(): evaluations must repeat exactly",
        )


def check_quantizer(quantizer: Quantizer, context: BuildContext | None = None, *, label: str = "quantizer") -> None:
    """A quantizer maps latents (B, embedding_dim, h, w) to a :class:`QuantizerOutput` of the same
    shape with integer codes (B, h, w) in [0, codebook_size), a finite scalar loss and a perplexity
    in [1, codebook_size]; it follows the context's latent width and reports its codebook size; one
    with a codebook counts usage since ``reset_usage`` and ``lookup(codes)`` gives the quantized latents."""
    context = context or DEFAULT_CONTEXT
    dim, size = quantizer.embedding_dim, quantizer.codebook_size
    _require(isinstance(dim, int) and dim >= 1, label, f"embedding_dim must be a positive int, got {dim!r}")
    _require(isinstance(size, int) and size >= 1, label, f"codebook_size must be a positive int, got {size!r}")
    if context.latent_dim:
        _require(
            dim == context.latent_dim,
            label,
            f"embedding_dim {dim} does not follow the context's "
            f"latent_dim {context.latent_dim} (the autoencoder's latents)",
        )
    _require(
        quantizer.context_facts().get("codebook_size") == size,
        label,
        f"context_facts() must report codebook_size={size}",
    )
    latents = _latents(quantizer)
    quantizer.eval()
    with torch.no_grad():
        quantizer.reset_usage()
        out = _call(label, "forward(latents)", lambda: quantizer(latents))
    _require(isinstance(out, QuantizerOutput), label, f"forward returned {type(out).__name__}, not QuantizerOutput")
    _require(
        tuple(out.quantized_BDhw.shape) == tuple(latents.shape),
        label,
        f"quantized latents have shape {tuple(out.quantized_BDhw.shape)}; expected {tuple(latents.shape)}",
    )
    _require(bool(torch.isfinite(out.quantized_BDhw).all()), label, "quantized latents have NaN or Inf values")
    codes = out.codes_Bhw
    _require(
        not codes.dtype.is_floating_point and codes.dtype != torch.bool and tuple(codes.shape) == (2, 4, 4),
        label,
        f"codes must be integers of shape (2, 4, 4), got {codes.dtype} {tuple(codes.shape)}",
    )
    _require(
        int(codes.min()) >= 0 and int(codes.max()) < size,
        label,
        f"codes must lie in [0, {size}); got min {int(codes.min())}, max {int(codes.max())}",
    )
    for what, value in (("loss", out.loss), ("perplexity", out.perplexity)):
        _require(
            isinstance(value, torch.Tensor) and value.numel() == 1 and bool(torch.isfinite(value).all()),
            label,
            f"{what} must be a finite scalar tensor, got {value!r}",
        )
    perplexity = float(out.perplexity)
    _require(1 - 1e-4 <= perplexity <= size * (1 + 1e-4), label, f"perplexity {perplexity:.4g} is outside [1, {size}]")
    usage = quantizer.usage_counts()
    if usage is not None:
        _require(
            tuple(usage.shape) == (size,) and int(usage.sum()) == codes.numel(),
            label,
            f"usage_counts() after reset_usage() and one forward of {codes.numel()} latents must be ({size},) "
            f"summing to {codes.numel()}, got shape {tuple(usage.shape)} summing to {int(usage.sum())}",
        )
        quantizer.reset_usage()
        _require(int(quantizer.usage_counts().sum()) == 0, label, "reset_usage() does not forget the usage counts")
        with torch.no_grad():
            looked_up = _call(label, "lookup(codes)", lambda: quantizer.lookup(codes))
        _assert_same(
            out.quantized_BDhw,
            looked_up,
            label,
            "lookup(codes) does not give the quantized latents forward returned for those codes",
        )


def check_discriminator(
    discriminator: Discriminator, context: BuildContext | None = None, *, label: str = "discriminator"
) -> None:
    """A discriminator scores images (B, C, H, W) in [-1, 1] with finite logits, one set per image."""
    context = context or DEFAULT_CONTEXT
    images = _images(2, context)
    discriminator.eval()
    with torch.no_grad():
        logits = _call(label, "forward(images)", lambda: discriminator(images))
    _require(
        isinstance(logits, torch.Tensor) and logits.ndim >= 1 and logits.shape[0] == 2,
        label,
        f"logits of 2 images must be a tensor with first dimension 2, got {tuple(getattr(logits, 'shape', ()))}",
    )
    _require(bool(torch.isfinite(logits).all()), label, "logits have NaN or Inf values")


class OracleDenoiser:
    """A denoiser that always predicts the same code grid with certainty: what every sampler must
    then return exactly (used by :func:`check_sampler` and :func:`check_generator`)."""

    def __init__(self, target_BL: torch.Tensor, num_codes: int) -> None:
        self.target_BL, self.num_codes, self.calls = target_BL, num_codes, 0

    def __call__(self, codes_t_BL: torch.Tensor, t_B: torch.Tensor) -> torch.Tensor:
        self.calls += 1
        onehot_BLC = torch.nn.functional.one_hot(self.target_BL[: len(codes_t_BL)], self.num_codes + 1).float()
        return torch.log(onehot_BLC.clamp_min(1e-30)).clamp_min(-70.0).transpose(1, 2)


class _ArgmaxSampler(Sampler):
    """A one-call sampler for :func:`check_generator`: the most likely code of the all-MASK prediction."""

    def sample(
        self,
        denoise: Callable[..., torch.Tensor],
        schedule: Any,
        *,
        length: int,
        steps: int,
        generators: list[torch.Generator],
    ) -> torch.Tensor:
        batch = len(generators)
        codes_t_BL = torch.full((batch, length), schedule.num_codes, dtype=torch.long)
        t_B = torch.full((batch,), schedule.num_steps - 1, dtype=torch.long)
        return denoise(codes_t_BL, t_B)[:, : schedule.num_codes].argmax(dim=1)


def _condition_tokens(batch: int, context: BuildContext, seed: int = 0, tokens: int = 2) -> ConditionTokens:
    generator = _generator(seed)
    return ConditionTokens(
        torch.randn(batch, tokens, context.cond_dim, generator=generator), torch.zeros(batch, dtype=torch.bool)
    )


def check_generator(generator: Generator, context: BuildContext | None = None, *, label: str = "generator") -> None:
    """A generator's training loss of random code grids (codebook_size, code_grid of the context) is a
    finite scalar whose gradient reaches its parameters, batch 1 included, and under bf16 autocast;
    it samples (B, H, W) codes in [0, codebook_size) with and without guidance, and the same
    generators give the same codes."""
    context = context or DEFAULT_CONTEXT
    size, grid_hw = context.codebook_size, image_hw(context.code_grid)
    _require(
        size >= 2 and min(grid_hw) >= 1, label, "check_generator needs a context with codebook_size >= 2 and code_grid"
    )
    codes_BHW = torch.randint(size, (3, *grid_hw), generator=_generator(1))
    generator.train()
    loss, scalars = _call(
        label,
        "training_loss",
        lambda: generator.training_loss(codes_BHW, _condition_tokens(3, context), generator=_generator(2)),
    )
    _require(
        isinstance(loss, torch.Tensor) and loss.ndim == 0 and bool(torch.isfinite(loss)),
        label,
        f"training_loss must return a finite scalar tensor, got {loss!r}",
    )
    _require(
        isinstance(scalars, dict) and all(isinstance(v, float) for v in scalars.values()),
        label,
        "training_loss must return a dict of floats to log next to the loss",
    )
    loss.backward()
    trained = [(name, p) for name, p in generator.named_parameters() if p.requires_grad]
    no_grad = [name for name, p in trained if p.grad is None or not bool(torch.isfinite(p.grad).all())]
    _require(trained and len(no_grad) < len(trained), label, "the loss's gradient reaches none of the parameters")
    generator.zero_grad(set_to_none=True)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        bf16, _ = _call(
            label,
            "training_loss under bf16 autocast",
            lambda: generator.training_loss(codes_BHW[:1], _condition_tokens(1, context), generator=_generator(3)),
        )
    _require(bool(torch.isfinite(bf16)), label, "training_loss of batch 1 under bf16 autocast is not finite")
    generator.eval()
    sampler = _ArgmaxSampler()
    for guidance in (1.0, 3.0):
        draws = lambda: [_generator(10 + row) for row in range(2)]  # noqa: E731
        condition, null = _condition_tokens(2, context), _condition_tokens(2, context, seed=5)
        first = _call(
            label,
            f"sample (guidance {guidance})",
            lambda: generator.sample(condition, sampler, steps=1, null=null, guidance=guidance, generators=draws()),
        )
        again = generator.sample(condition, sampler, steps=1, null=null, guidance=guidance, generators=draws())
        _require(
            tuple(first.shape) == (2, *grid_hw) and not first.dtype.is_floating_point,
            label,
            f"sample must return integer codes (2, {grid_hw[0]}, {grid_hw[1]}), got {first.dtype} {tuple(first.shape)}",
        )
        _require(bool(((first >= 0) & (first < size)).all()), label, f"sampled codes outside [0, {size})")
        _require(torch.equal(first, again), label, "the same generators gave different codes")


def check_sampler(
    sampler: Sampler, context: BuildContext | None = None, *, schedule: Any, label: str = "sampler"
) -> None:
    """With ``schedule`` (a generator's forward process: ``num_codes``, ``num_steps``, ``mask_index``,
    ``posterior``), a sampler returns exactly the code grid an oracle denoiser predicts with
    certainty, for 1, 2 and 10 steps and a 1-token grid, without MASK; it calls the denoiser at
    most ``steps`` times, and a row's result does not depend on the other rows of its batch.
    :func:`check_plugin` takes the schedule from a registered generator (see
    :func:`schedule_from_host`)."""
    size = schedule.num_codes
    for length, steps in ((16, 1), (16, 2), (16, min(10, schedule.num_steps)), (1, 3)):
        target_BL = torch.randint(size, (3, length), generator=_generator(length + steps))
        oracle = OracleDenoiser(target_BL, size)
        codes = _call(
            label,
            f"sample ({steps} steps, {length} tokens)",
            lambda: sampler.sample(
                oracle, schedule, length=length, steps=steps, generators=[_generator(row) for row in range(3)]
            ),
        )
        _require(
            torch.equal(codes.long(), target_BL),
            label,
            f"with a certain denoiser, {steps} steps on {length} tokens must give exactly its prediction",
        )
        _require(oracle.calls <= steps, label, f"called the denoiser {oracle.calls} times for steps={steps}")
    # Row 1 alone (with its own generator) equals row 1 of a batch of 3, for an uncertain denoiser.
    logits_BCL = torch.randn(3, size + 1, 16, generator=_generator(99))
    logits_BCL[:, size] = -70.0

    def uncertain(codes_t_BL: torch.Tensor, t_B: torch.Tensor) -> torch.Tensor:
        rows = logits_BCL[: len(codes_t_BL)] if len(codes_t_BL) == 3 else logits_BCL[1:2]
        return torch.log_softmax(rows, dim=1).clamp_min(-70.0)

    batch = sampler.sample(uncertain, schedule, length=16, steps=4, generators=[_generator(20 + r) for r in range(3)])
    alone = sampler.sample(uncertain, schedule, length=16, steps=4, generators=[_generator(21)])
    _require(
        torch.equal(batch[1:2], alone),
        label,
        "a row's codes changed with the rest of its batch (draw each row's randomness from its own generator)",
    )
    _require(bool((batch < size).all()), label, "the output holds MASK tokens")


def schedule_from_host(host: PluginHost, context: BuildContext | None = None) -> Any:
    """The forward process of the first registered generator that has one (``generator.schedule``),
    built in ``context`` with its default options; None when no generator has a schedule."""
    context = context or DEFAULT_CONTEXT
    for name in host.registry("generator").names():
        try:
            generator = host.build("generator", {"name": name}, context)
        except (VqtouchError, MissingWeightsError):
            continue
        if hasattr(generator, "schedule"):
            return generator.schedule
    return None


def _check_sampler_with_host(sampler: Sampler, context: BuildContext, *, label: str, host: PluginHost) -> None:
    schedule = schedule_from_host(host, context)
    if schedule is None:
        _skip(
            f"{label}: no installed generator provides a forward process (generator.schedule) to sample from",
            VqtouchError("no generator"),
        )
    check_sampler(sampler, context, schedule=schedule, label=label)


def check_clusterer(clusterer: Clusterer, context: BuildContext | None = None, *, label: str = "clusterer") -> None:
    """A clusterer's ``fit`` and ``predict`` return one integer cluster index per feature row."""
    features = _features()
    with torch.no_grad():
        fitted = _call(label, "fit(features)", lambda: clusterer.fit(features))
        predicted = _call(label, "predict(features)", lambda: clusterer.predict(features))
    for what, value in (("fit", fitted), ("predict", predicted)):
        _require(
            isinstance(value, torch.Tensor)
            and tuple(value.shape) == (len(features),)
            and not value.dtype.is_floating_point,
            label,
            f"{what} of ({len(features)}, F) features must return ({len(features)},) integer indices, got "
            f"{getattr(value, 'dtype', type(value).__name__)} {tuple(getattr(value, 'shape', ()))}",
        )


def check_metric(metric: Metric, context: BuildContext | None = None, *, label: str = "metric") -> None:
    """A metric scores identical images strictly better than noisy ones (``higher_is_better`` says
    which way), returns a finite float, accumulates every ``update`` and forgets on ``reset``.

    A metric built as skipped (``metric.skipped``: a file or package it needs is missing) must say
    why in a message that names what to provide; its behaviour cannot be checked here, so check
    it again with its weights (the built-ins' suite does, with files of the real layout)."""
    context = context or DEFAULT_CONTEXT
    _require(isinstance(metric.higher_is_better, bool), label, "higher_is_better must be a bool")
    if metric.skipped is not None:
        _require(
            isinstance(metric.skipped, str) and len(metric.skipped.strip()) >= 20,
            label,
            f"a skipped metric must say what is missing and how to provide it, got {metric.skipped!r}",
        )
        return
    # Smooth images (random 4x4 colour fields, upsampled): white noise plus noise is still white noise,
    # which a metric comparing image *sets* (FID, KID) rightly cannot tell apart.
    coarse = torch.rand(4, 3, 4, 4, generator=_generator(2))
    target = torch.nn.functional.interpolate(
        coarse, size=image_hw(context.image_size), mode="bilinear", align_corners=False
    )
    noisy = (target + 0.2 * torch.randn(target.shape, generator=_generator(3))).clamp(0, 1)

    def score(*pairs: tuple[torch.Tensor, torch.Tensor]) -> float:
        metric.reset()
        for predicted, reference in pairs:
            _call(label, "update", lambda p=predicted, r=reference: metric.update(p, r))
        value = _call(label, "compute", metric.compute)
        _require(
            isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value),
            label,
            f"compute() must return a finite float, got {value!r}",
        )
        return float(value)

    same = score((target, target))
    worse = score((noisy, target))
    better = same > worse if metric.higher_is_better else same < worse
    _require(
        better,
        label,
        f"identical images score {same:.6g} and noisy ones {worse:.6g}: identical images must "
        f"score the best value ({'higher' if metric.higher_is_better else 'lower'} is better)",
    )
    _require(
        _close(score((target, target)), same),
        label,
        "after reset(), identical images score differently than the first time: reset() must forget "
        "everything seen (and compute must be deterministic)",
    )
    mixed = score((target, target), (noisy, target))
    _require(not _close(mixed, same), label, "a second update() did not change the result: every update must count")
    _require(not _close(mixed, worse), label, "a second update() replaced the first: updates must accumulate")
    metric.reset()


def check_dataset(dataset: TactileDataset, image_size: ImageSize | None = None, *, label: str = "dataset") -> None:
    """A dataset is non-empty and every sample is a dict with the documented entries: ``tactile``
    (3, H, W) float in [0, 1] (and an optional ``visual`` of the same shape), an int ``label`` in
    [-1, num_classes), str ``text``, non-empty str ``sensor`` and ``id`` (further entries are
    allowed); reading a sample twice gives the same sample and ``context_facts`` reports the class
    count.  ``image_size``: the S or (H, W) samples must have (None: any)."""
    length = _call(label, "len(dataset)", lambda: len(dataset))
    _require(isinstance(length, int) and length > 0, label, f"len(dataset) must be a positive int, got {length!r}")
    names = dataset.class_names
    _require(
        isinstance(names, list) and all(isinstance(n, str) for n in names), label, "class_names must be a list of str"
    )
    _require(
        dataset.context_facts().get("num_classes") == len(names),
        label,
        f"context_facts() must report num_classes={len(names)} (len(class_names))",
    )
    for index in sorted({0, length - 1}):
        sample = _call(label, f"dataset[{index}]", lambda i=index: dataset[i])
        where = f"sample {index}"
        _require(isinstance(sample, dict), label, f"{where} is a {type(sample).__name__}, not a dict")
        missing = [key for key in SAMPLE_KEYS if key not in sample]
        _require(
            not missing,
            label,
            f"{where} lacks {missing} (every sample has {', '.join(SAMPLE_KEYS)}; visual is optional)",
        )
        tactile = sample["tactile"]
        _require(
            isinstance(tactile, torch.Tensor)
            and tactile.dtype.is_floating_point
            and tactile.ndim == 3
            and tactile.shape[0] == 3,
            label,
            f"{where}: tactile must be a float tensor (3, H, W), got "
            f"{getattr(tactile, 'dtype', type(tactile).__name__)} {tuple(getattr(tactile, 'shape', ()))}",
        )
        if image_size is not None:
            _require(
                tuple(tactile.shape[-2:]) == image_hw(image_size),
                label,
                f"{where}: tactile is {tactile.shape[-2]}x{tactile.shape[-1]} px but the experiment's image "
                f"size is {size_text(image_size)}",
            )
        for key in ("tactile", *(k for k in OPTIONAL_SAMPLE_KEYS if k in sample)):
            image = sample[key]
            _require(
                isinstance(image, torch.Tensor) and tuple(image.shape) == tuple(tactile.shape),
                label,
                f"{where}: {key} must have the tactile image's shape {tuple(tactile.shape)}",
            )
            _require(
                bool(torch.isfinite(image).all()) and float(image.min()) >= 0 and float(image.max()) <= 1,
                label,
                f"{where}: {key} has values outside [0, 1]",
            )
        value = sample["label"]
        _require(
            type(value) is int and -1 <= value < len(names) and (names or value == -1),
            label,
            f"{where}: label must be an int in [-1, {len(names)}) (-1: none), got {value!r}",
        )
        _require(isinstance(sample["text"], str), label, f"{where}: text must be a str")
        for key in ("sensor", "id"):
            _require(
                isinstance(sample[key], str) and bool(sample[key]), label, f"{where}: {key} must be a non-empty str"
            )
        again = _call(label, f"dataset[{index}] again", lambda i=index: dataset[i])
        _require(
            again["id"] == sample["id"] and torch.equal(again["tactile"], tactile),
            label,
            f"reading sample {index} twice gave different samples",
        )


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
)


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

"""Experiment configuration: strict sections, plugin slots and how configs are resolved.

An experiment is described by one config: core's :class:`ExperimentConfig` plus one section
per registered stage (``PluginHost.experiment_model``).  Wherever a plugin is chosen (a
*slot*: ``sensor``, ``tokenizer.autoencoder``, ``generator.conditioners``, ...), the block is
a mapping with a ``name`` key; the rest of the block is validated against that plugin's own
options model, taken from the host's registries, as soon as the config is loaded.

Resolution order (later wins): scene preset -> config files (TOML or JSON, in order) ->
``--set path=value`` overrides.  Selecting another plugin for a slot (changing its
``name``) resets that slot's options instead of mixing two plugins' options.
"""

from __future__ import annotations

import copy
import json
import tomllib
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
import types
import typing
from dataclasses import dataclass
from typing import TYPE_CHECKING, Annotated, Any, Literal, Union

from pydantic import AfterValidator, BaseModel, Field, SerializeAsAny, ValidationError, ValidationInfo, WrapValidator
from pydantic_core import PydanticCustomError

from .deprecations import CONFIG_REMOVED, CONFIG_RENAMES, RENAMED_IN, STAGES_REMOVED, ConfigRename, warn_renamed
from .errors import (
    ConfigError,
    PluginError,
    UnknownPluginError,
    format_validation_error,
    one_line,
    unknown_name_message,
)
from .image_size import ImageSizeOption
from .plugin_config import PluginConfig, StrictModel

#: The largest seed: NumPy takes seeds below 2**32, and the seeds vqtouch derives from one
#: (``seed * 1_000_003 + index`` for each generated image, ...) then stay within 64 bits.
SEED_MAX = 2**32 - 1

if TYPE_CHECKING:
    from .plugin_manager import PluginHost


@dataclass(frozen=True)
class SlotMarker:
    """Annotation metadata marking a config field as a plugin slot of registry ``kind``."""

    kind: str


@dataclass(frozen=True)
class SlotInfo:
    """One slot of the experiment config: its dotted path, registry kind and whether it is a list."""

    path: str
    kind: str
    many: bool


def _host_from(info: ValidationInfo) -> Any:
    context = info.context if isinstance(info.context, Mapping) else {}
    host = context.get("host")
    if host is None:
        # No hidden global host: which plugins exist must be decided by the caller.
        raise PydanticCustomError(
            "no_plugin_host",
            "validating a plugin slot needs the PluginHost whose registries to use: pass it in the "
            "validation context under the key 'host' (see vqtouch.core.validate_experiment)",
        )
    return host


def _slot_validator(kind: str) -> Any:
    def validate(value: Any, handler: Any, info: ValidationInfo) -> PluginConfig:
        # The registry normalises the block (a name, a mapping or a config object) and picks the model.
        try:
            return _host_from(info).registry(kind).validate_config(value, context=info.context)
        except UnknownPluginError as exc:
            raise PydanticCustomError("unknown_plugin", "{message}", {"message": str(exc)}) from None

    return validate


def Slot(kind: str) -> Any:  # noqa: N802 - reads like a type in annotations
    """Annotation for a field holding the options of one plugin of registry ``kind``.

    Use ``Slot("quantizer") | None`` for a single slot and ``list[Slot("metric")]`` for a
    list slot; the config machinery finds slots through this annotation, so a stage's
    section declares its slots simply by having such fields.
    """
    return Annotated[SerializeAsAny[PluginConfig], WrapValidator(_slot_validator(kind)), SlotMarker(kind)]


def _slot_in(annotation: Any) -> tuple[str, bool] | None:
    """(kind, many) when ``annotation`` is a Slot, an optional Slot or a list of Slots."""
    origin = typing.get_origin(annotation)
    if origin is Annotated:
        for meta in annotation.__metadata__:
            if isinstance(meta, SlotMarker):
                return meta.kind, False
        return _slot_in(typing.get_args(annotation)[0])
    if origin in (list, tuple):
        inner = _slot_in(typing.get_args(annotation)[0])
        return (inner[0], True) if inner else None
    if origin in (Union, types.UnionType):
        for arg in typing.get_args(annotation):
            found = _slot_in(arg)
            if found:
                return found
    return None


def slots_of(model: type[BaseModel], prefix: str = "") -> dict[str, SlotInfo]:
    """Every slot of a config model, by dotted path, found from the fields' annotations.

    Sections nested in sections are searched; plugin configs are not (their own slots, if
    any, belong to the plugin).
    """
    found: dict[str, SlotInfo] = {}
    for name, field in model.model_fields.items():
        path = f"{prefix}{name}"
        slot = _slot_in(field.annotation) or next(
            ((meta.kind, False) for meta in field.metadata if isinstance(meta, SlotMarker)), None
        )
        if slot is not None:
            found[path] = SlotInfo(path, *slot)
        elif isinstance(field.annotation, type) and issubclass(field.annotation, Section):
            found.update(slots_of(field.annotation, prefix=f"{path}."))
    return found


class Section(StrictModel):
    """Base of every config section (strict: unknown keys list the allowed ones).

    A stage plugin's own section (``tokenizer``, ``generator``, ...) subclasses it; its
    fields may be plain options, nested sections or slots (:func:`Slot`).
    """


class DataConfig(Section):
    """Where the training and evaluation images come from and how they are shaped."""

    dataset: Slot("dataset") | None = Field(
        None,
        description="Dataset plugin and its options: a reader of real data (e.g. touch_and_go with its root) "
        "or the embedded procedural scenes, which render with the experiment's sensor.",
    )
    # Strict: in lax mode `true` would validate as 1 (and `false` as val_fraction 0) or "16" as
    # 16, a config that runs but is not what was written.  Strict floats still take integers.
    image_size: ImageSizeOption = Field(
        64,
        description="Size of the images fed to the models, in pixels: 64 for 64x64, or [height, width] such as "
        "[240, 320] for a sensor's native aspect (readers crop to that aspect, then resize).",
    )
    batch_size: int = Field(16, ge=1, le=65536, strict=True, description="Images per optimisation step (per process).")
    num_workers: int = Field(
        0, ge=0, le=256, strict=True, description="DataLoader worker processes (0 loads in the main process)."
    )
    val_fraction: float = Field(
        0.1,
        ge=0.0,
        lt=1.0,
        strict=True,
        description="Fraction of samples held out for evaluation; 0 trains on every "
        "sample and skips the held-out evaluation.",
    )
    train_samples: int | None = Field(
        None,
        ge=1,
        strict=True,
        description="Train on only this many samples of the training split (a seeded draw: with one seed, a "
        "smaller count is a subset of a larger one); the held-out split does not change.  None: "
        "every training sample.  What `vqtouch evaluate reconstruction --out` varies.",
    )


def _known_stages(stages: list[str], info: ValidationInfo) -> list[str]:
    host = (info.context or {}).get("host") if isinstance(info.context, Mapping) else None
    if host is None:
        return stages
    for name in stages:
        if name not in host.stages:
            raise PydanticCustomError(
                "unknown_plugin", "{message}", {"message": unknown_name_message("stage", name, host.stages)}
            )
    if len(set(stages)) != len(stages):
        raise PydanticCustomError("repeated_stage", "a stage is listed twice: {stages}", {"stages": stages})
    return stages


class ExperimentConfig(Section):
    """One experiment: which stages run, the experiment's sensors, data and metrics.

    This base holds what every stage shares.  Each registered stage with a config section
    adds a field of that name (``tokenizer``, ``generator``, ...): the model a host
    validates with is :attr:`PluginHost.experiment_model`, a subclass of this one.  Every
    slot is a mapping ``{"name": <plugin>, ...options}``; a run builds only the slots its
    stages need.
    """

    schema_version: Literal[1] = Field(1, description="Version of this configuration schema.")
    name: str = Field(
        "experiment",
        min_length=1,
        max_length=100,
        pattern=r"^[A-Za-z0-9._-]+$",
        description="Experiment name, used in the run directory name.",
    )
    scene: str | None = Field(None, description="Scene preset this config started from (informational).")
    description: str = Field("", description="Free text describing the experiment.")
    stages: Annotated[list[str], AfterValidator(_known_stages)] = Field(
        default_factory=list,
        description="Pipeline stages this experiment runs, in order (see `vqtouch config stages`).",
    )
    seed: int = Field(0, ge=0, le=SEED_MAX, description="Seed for every random number generator.")
    deterministic: bool = Field(False, description="Ask PyTorch for deterministic algorithms (slower).")
    device: Literal["auto", "cpu", "cuda"] = Field("auto", description="Compute device; auto picks CUDA when present.")
    output_dir: str = Field("runs", min_length=1, description="Folder under which run directories are created.")
    sensor: Slot("sensor_family") | None = Field(
        None,
        description="The experiment's sensor: the family (and variant) whose images the data are, or that "
        "renders them (procedural scenes). The one source of truth for the source sensor.",
    )
    target_sensor: Slot("sensor_family") | None = Field(
        None, description="The unseen sensor a cross-sensor scene adapts to (few-shot, zero-shot, cross-sensor)."
    )
    paired_sensor: Slot("sensor_family") | None = Field(
        None,
        description="A second sensor that renders the same contacts as `sensor`: datasets that can render "
        "pairs add its image of each sample as 'tactile_source' (the source image of touch-to-touch "
        "generation, e.g. GelSight -> DIGIT with sensor=digit, paired_sensor=gelsight).",
    )
    data: DataConfig = Field(default_factory=DataConfig, description="Data source and shapes.")
    metrics: list[Slot("metric")] = Field(
        default_factory=list, description="Image metrics that stages report (e.g. psnr, ssim)."
    )

    def slot(self, path: str) -> PluginConfig | list[PluginConfig] | None:
        """The config in slot ``path`` (e.g. ``"tokenizer.quantizer"``)."""
        value: Any = self
        for part in path.split("."):
            value = getattr(value, part)
        return value

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-ready dict (plugin options included)."""
        return self.model_dump(mode="json")


# -- loading and merging --------------------------------------------------------------------


def load_config_file(path: str | Path) -> dict[str, Any]:
    """Read a TOML or JSON config file into a dict; errors name the file and the problem."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file {str(path)!r} does not exist")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        # TOML and JSON are UTF-8 by definition; a file saved in another encoding is the usual cause.
        raise ConfigError(
            f"{path}: not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at position {exc.start}); "
            "save it as UTF-8 (TOML and JSON config files are UTF-8)"
        ) from None
    suffix = path.suffix.lower()
    try:
        if suffix == ".toml":
            data = tomllib.loads(text)
        elif suffix == ".json":
            data = json.loads(text)
        elif suffix in {".yaml", ".yml"}:
            try:
                import yaml
            except ImportError:
                raise ConfigError(f"{path}: YAML configs need PyYAML (pip install pyyaml), or use TOML/JSON") from None
            data = yaml.safe_load(text)
        else:
            raise ConfigError(f"{path}: unsupported config format {suffix!r}; use .toml or .json")
    except (tomllib.TOMLDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f"{path}: cannot parse: {exc}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: the top level must be a table/object, got {type(data).__name__}")
    return data


def merge_configs(base: Mapping[str, Any], update: Mapping[str, Any]) -> dict[str, Any]:
    """Deep-merge ``update`` into a copy of ``base``.

    A block whose ``name`` changes is replaced whole: a new plugin never inherits the
    options of the one it replaces.
    """
    merged = copy.deepcopy(dict(base))
    for key, value in update.items():
        current = merged.get(key)
        if _merges_into(current, value):
            merged[key] = merge_configs(current, value)
        else:
            merged[key] = copy.deepcopy(value)
    return merged


def _merges_into(current: Any, update: Any) -> bool:
    both = isinstance(current, dict) and isinstance(update, Mapping)
    return both and not ("name" in current and "name" in update and current["name"] != update["name"])


def parse_override(text: str) -> tuple[list[str], Any]:
    """Split ``a.b=value`` into its key path and value (JSON if it parses, else a string)."""
    key, sep, raw = text.partition("=")
    key = key.strip()
    if not sep or not key or any(not part for part in key.split(".")):
        raise ConfigError(f"bad override {text!r}: expected PATH=VALUE, e.g. --set tokenizer.train.steps=200")
    try:
        value = json.loads(raw)
    except json.JSONDecodeError:
        value = raw
    return key.split("."), value


def apply_override(config: dict[str, Any], path: Sequence[str], value: Any) -> dict[str, Any]:
    """Set ``path`` to ``value`` in a copy of ``config``; setting a slot's ``name`` resets the slot."""
    result = copy.deepcopy(config)
    node: Any = result
    for depth, part in enumerate(path[:-1]):
        if isinstance(node, list):
            index = _list_index(part, node, path[: depth + 1])
            node = node[index]
            continue
        child = node.get(part)
        if child is None:
            child = node[part] = {}
        elif not isinstance(child, (dict, list)):
            raise ConfigError(
                f"cannot set {'.'.join(path)}: {'.'.join(path[: depth + 1])} is "
                f"{type(child).__name__} {child!r}, not a section"
            )
        node = child
    last = path[-1]
    if isinstance(node, list):
        node[_list_index(last, node, path)] = value
    elif last == "name" and len(path) > 1 and "name" in node and node["name"] != value:
        node.clear()
        node["name"] = value
    elif _merges_into(node.get(last), value):
        node[last] = merge_configs(node[last], value)
    else:
        node[last] = value
    return result


def _list_index(part: str, node: list[Any], where: Sequence[str]) -> int:
    if not part.isdigit() or int(part) >= len(node):
        raise ConfigError(f"cannot set {'.'.join(where)}: index {part!r} is not within a list of {len(node)}")
    return int(part)


def validate_experiment(data: Mapping[str, Any], host: PluginHost) -> ExperimentConfig:
    """Validate a raw dict into the host's experiment model (its stages' sections included)
    against ``host``'s registries.

    Afterwards every plugin's ``vqtouch_validate_experiment`` hook may veto the combination.
    """
    data = migrate_config(data, host.stages, host.experiment_model)
    stages = data.get("stages")
    # An unknown stage first: it also explains its section being an unknown option (a scene of a
    # stage whose plugin is not installed carries that stage's section).
    for name in stages if isinstance(stages, list) else []:
        if isinstance(name, str) and name not in host.stages:
            raise ConfigError(f"invalid configuration: stages: {unknown_name_message('stage', name, host.stages)}")
    try:
        config = host.experiment_model.model_validate(dict(data), context={"host": host})
    except ValidationError as exc:
        raise ConfigError(format_validation_error(exc)) from None
    # One implementation at a time, so an unexpected error names the plugin that raised it.
    for impl in host.pm.hook.vqtouch_validate_experiment.get_hookimpls():
        try:
            impl.function(config=config)
        except ConfigError:
            raise
        except Exception as exc:  # noqa: BLE001 - a plugin's bug, reported in one line naming it
            source = host.sources.get(impl.plugin_name)
            who = source.describe() if source is not None else f"plugin {impl.plugin_name!r}"
            raise PluginError(
                f"{who} failed in vqtouch_validate_experiment: {type(exc).__name__}: "
                f"{one_line(str(exc))}; fix or update that plugin, or block it with "
                f"VQTOUCH_BLOCK_PLUGINS={impl.plugin_name}"
            ) from exc
    return config


def resolve_config(
    scene: str | None = None,
    files: Iterable[str | Path] = (),
    overrides: Iterable[str] = (),
    *,
    host: PluginHost,
    default_scene: str | None = None,
    scene_required: bool = False,
) -> ExperimentConfig:
    """Build the experiment config from a scene preset, config files and ``--set`` overrides.

    A config file that names a ``scene`` (a recipe: ``scene = "tour"`` at its top) is merged over that
    scene when ``scene`` is None; a different ``scene`` given beside it is refused in one line.  With
    neither, ``default_scene`` (a command's default); ``scene_required``: none at all is a ConfigError."""
    files = list(files)
    loaded = [load_config_file(path) for path in files]
    scene = recipe_scene(scene, files, loaded) or default_scene
    if scene_required and scene is None:
        raise ConfigError("name a scene, e.g. `vqtouch config show reconstruction` (list: `vqtouch config scenes`)")
    data: dict[str, Any] = {}
    if scene is not None:
        entry = host.scene(scene)
        data = merge_configs({"name": scene, "scene": scene, "description": entry.description}, entry.config)
    for file_data in loaded:
        data = merge_configs(data, file_data)
    applied: list[tuple[str, list[str]]] = []
    for text in overrides:
        key_path, value = parse_override(text)
        _refuse_lost_overrides(data, key_path, value, applied, text)
        data = apply_override(data, key_path, value)
        applied.append((text, key_path))
    return validate_experiment(data, host)


def recipe_scene(scene: str | None, files: list[str | Path], loaded: list[dict[str, Any]]) -> str | None:
    """The scene a config is built over: ``scene``, else the one the config files name (they must agree)."""
    named = [(str(path), data["scene"]) for path, data in zip(files, loaded) if data.get("scene") is not None]
    for path, file_scene in named:
        if scene is not None and file_scene != scene:
            raise ConfigError(
                f"{path} is a recipe over scene {file_scene!r}, but scene {scene!r} was given; give "
                f"--scene {file_scene} or none"
            )
        scene = file_scene
    return scene


def _refuse_lost_overrides(
    data: dict[str, Any], path: list[str], value: Any, applied: list[tuple[str, list[str]]], text: str
) -> None:
    """ConfigError when ``path=value`` selects another plugin for a slot whose options an earlier
    ``--set`` changed: the reset would silently drop them (and run something the user did not ask for)."""
    if path[-1] == "name" and len(path) > 1:
        slot, new_name = path[:-1], value
    elif isinstance(value, Mapping) and "name" in value:
        slot, new_name = path, value["name"]
    elif isinstance(value, str):  # `--set slot=plugin`
        slot, new_name = path, value
    else:
        return
    node: Any = data
    for part in slot:
        if isinstance(node, dict):
            node = node.get(part)
        elif isinstance(node, list) and part.isdigit() and int(part) < len(node):  # an item of a list slot
            node = node[int(part)]
        else:
            node = None
    if not isinstance(node, dict) or node.get("name") in (None, new_name):
        return
    depth = len(slot)
    lost = [
        earlier
        for earlier, earlier_path in applied
        if len(earlier_path) > depth and earlier_path[:depth] == slot and earlier_path[depth] != "name"
    ]
    if lost:
        where = ".".join(slot)
        raise ConfigError(
            f"--set {text} selects another plugin for {where}, which resets its options and would "
            f"drop the earlier {', '.join('--set ' + t for t in lost)}; put --set {text} before them"
        )


# -- configs written for vqtouch 0.1.0 ---------------------------------------------------------


def migrate_config(
    data: Mapping[str, Any], registered_stages: Iterable[str] = (), experiment_model: type[BaseModel] = ExperimentConfig
) -> dict[str, Any]:
    """``data`` with every 0.1.0 key moved to its new place (one warning each), or ConfigError
    naming a removed key or stage and what replaced it.  Today's configs come back unchanged.
    ``registered_stages``: stage names installed now (a plugin may register a removed name anew);
    ``experiment_model``: the host's config model (which tells a section's keys from a plugin's)."""
    registered = set(registered_stages)
    migrated = copy.deepcopy(dict(data))
    for key, advice in CONFIG_REMOVED.items():
        if key in migrated:
            raise ConfigError(f"config key {key!r} (vqtouch 0.1.0) {advice}")
    for rename in CONFIG_RENAMES:
        _apply_rename(migrated, rename, experiment_model)
    stages = migrated.get("stages")
    for stage in stages if isinstance(stages, list) else []:
        if isinstance(stage, str) and stage in STAGES_REMOVED and stage not in registered:
            raise ConfigError(f"stage {stage!r} (vqtouch 0.1.0) was removed in {RENAMED_IN}: {STAGES_REMOVED[stage]}")
    return migrated


def _apply_rename(data: dict[str, Any], rename: ConfigRename, experiment_model: type[BaseModel]) -> None:
    *old_parents, old_key = rename.old.split(".")
    parent = _node(data, old_parents)
    if not isinstance(parent, dict) or old_key not in parent:
        return
    value = parent[old_key]
    *new_parents, new_key = rename.new.split(".")
    if rename.only_plugin_block:
        if not (isinstance(value, Mapping) and "name" in value):
            return
        # The old block may have been merged into today's section of the same name (a file or --set over
        # a scene): only the keys that are not the section's own are the plugin's.
        section_keys = _section_fields(experiment_model, rename.old)
        kept = {key: item for key, item in value.items() if key in section_keys}
        value = {key: item for key, item in value.items() if key not in section_keys}
        parent[old_key] = kept
    else:
        del parent[old_key]
    if rename.as_list:
        value = list(value) if isinstance(value, list) else [value]
    warn_renamed(rename.old, rename.new, what="config key", stacklevel=5)
    target = data
    for part in new_parents:
        child = target.get(part)
        if child is None:
            child = target[part] = {}
        elif not isinstance(child, dict):
            raise ConfigError(
                f"config key {rename.old!r} moved to {rename.new!r}, but {part!r} is "
                f"{type(child).__name__} {child!r} here; write it under {rename.new!r}"
            )
        target = child
    current = target.get(new_key)
    # Only a user's file or --set can hold an old key, so it is what they asked for: it goes over what
    # a scene put at the new key (a block naming another plugin replaces it whole).
    target[new_key] = (
        merge_configs(current, value) if isinstance(current, dict) and isinstance(value, Mapping) else value
    )


def _section_fields(model: type[BaseModel], path: str) -> set[str]:
    """The keys of the config section at dotted ``path`` of ``model`` (empty when it is no section)."""
    for part in path.split("."):
        field = model.model_fields.get(part)
        annotation = field.annotation if field is not None else None
        if not (isinstance(annotation, type) and issubclass(annotation, BaseModel)):
            return set()
        model = annotation
    return set(model.model_fields)


def _node(data: Any, path: list[str]) -> Any:
    for part in path:
        if not isinstance(data, dict):
            return None
        data = data.get(part)
    return data


# -- the demo's size ------------------------------------------------------------------------------

#: Caps on core's own options for ``vqtouch demo`` (plugins and stages declare their own caps
#: when they register: ``demo={...}``).
CORE_DEMO_CAPS = {"data.batch_size": 8}


def _capped(data: dict[str, Any], path: str, cap: Any) -> None:
    """Lower the number at ``path`` of the nested dict ``data`` to ``cap`` (other values are left alone)."""
    *parents, last = path.split(".")
    node = _node(data, parents)
    if isinstance(node, dict) and isinstance(node.get(last), (int, float)) and not isinstance(node.get(last), bool):
        node[last] = min(node[last], cap)


def scale_for_demo(config: ExperimentConfig, host: PluginHost) -> ExperimentConfig:
    """``config`` scaled down to minutes on a laptop CPU: core's caps, each stage's ``demo`` caps on
    its section and each selected plugin's ``demo`` caps on its options."""
    data = config.to_dict()
    for path, cap in CORE_DEMO_CAPS.items():
        _capped(data, path, cap)
    for name in config.stages:
        for path, cap in host.stage(name).demo.items():
            _capped(data, f"{name}.{path}", cap)
    for path, info in host.slots.items():
        value = config.slot(path)
        for index, item in enumerate(value) if info.many else [(None, value)]:
            if item is None:
                continue
            prefix = path if index is None else f"{path}.{index}"
            for option, cap in host.registry(info.kind).get(item.name).demo.items():
                node = data
                for part in prefix.split("."):
                    node = node[int(part)] if isinstance(node, list) else node[part]
                _capped(node, option, cap)
    return validate_experiment(data, host)

"""Experiment configuration: strict sections, plugin slots and how configs are resolved.

An experiment is described by one :class:`ExperimentConfig`.  Wherever a plugin is chosen
(a *slot*: ``sensor``, ``tokenizer.encoder``, ``conditioner``, ...), the block is a
mapping with a ``name`` key; the rest of the block is validated against that plugin's own
options model, taken from the live registries, as soon as the config is loaded.

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
from typing import Annotated, Any, Literal

from pydantic import Field, SerializeAsAny, ValidationError, ValidationInfo, WrapValidator
from pydantic_core import PydanticCustomError

from .errors import ConfigError, UnknownPluginError
from .plugin_config import PluginConfig, StrictModel

Stage = Literal["render", "tokenizer", "reconstruct", "cluster", "adapt", "generator", "evaluate"]

#: The plugin slots each pipeline stage needs; a run builds only these (scene minimality).
STAGE_SLOTS: dict[str, tuple[str, ...]] = {
    "render": ("sensor", "data.dataset"),
    "tokenizer": ("data.dataset", "tokenizer.encoder", "tokenizer.quantizer", "tokenizer.discriminator"),
    "reconstruct": ("data.dataset", "tokenizer.encoder", "tokenizer.quantizer"),
    "cluster": ("data.dataset", "tokenizer.encoder", "tokenizer.quantizer", "clusterer"),
    "adapt": ("data.dataset", "tokenizer.encoder", "tokenizer.quantizer", "sensor", "target_sensor"),
    "generator": ("data.dataset", "tokenizer.encoder", "tokenizer.quantizer", "conditioner", "generator"),
    "evaluate": ("metrics",),
}

#: Slots a stage uses when they are set but can run without.
OPTIONAL_SLOTS = frozenset({"tokenizer.discriminator"})

#: Registry kind behind every slot path.
SLOT_KINDS: dict[str, str] = {
    "sensor": "sensor_family",
    "target_sensor": "sensor_family",
    "data.dataset": "dataset",
    "tokenizer.encoder": "encoder",
    "tokenizer.quantizer": "quantizer",
    "tokenizer.discriminator": "discriminator",
    "conditioner": "conditioner",
    "generator": "generator",
    "clusterer": "clusterer",
    "metrics": "metric",
}


def _host_from(info: ValidationInfo) -> Any:
    context = info.context if isinstance(info.context, Mapping) else {}
    host = context.get("host")
    if host is None:
        from .plugin_manager import default_host

        host = default_host()
    return host


def _slot_validator(kind: str) -> Any:
    def validate(value: Any, handler: Any, info: ValidationInfo) -> PluginConfig:
        registry = _host_from(info).registry(kind)
        if isinstance(value, str):
            value = {"name": value}
        if isinstance(value, PluginConfig):
            value = value.model_dump()
        if not isinstance(value, Mapping) or "name" not in value:
            raise PydanticCustomError(
                "missing_plugin_name", "a {kind} block needs a 'name' key choosing the plugin; available: {available}",
                {"kind": kind, "available": ", ".join(registry.names()) or "(none installed)"})
        try:
            registry.get(str(value["name"]))
        except UnknownPluginError as exc:
            raise PydanticCustomError("unknown_plugin", "{message}", {"message": str(exc)}) from None
        return registry.validate_config(dict(value), context=info.context)
    return validate


def Slot(kind: str) -> Any:  # noqa: N802 - reads like a type in annotations
    """Annotation for a field holding the options of one plugin of registry ``kind``."""
    return Annotated[SerializeAsAny[PluginConfig], WrapValidator(_slot_validator(kind))]


class Section(StrictModel):
    """Base of every config section (strict: unknown keys list the allowed ones)."""


class DataConfig(Section):
    """Where the training and evaluation images come from and how they are shaped."""

    dataset: Slot("dataset") | None = Field(
        None, description="Dataset plugin and its options: a reader of real data (e.g. touch_and_go with its root) "
                          "or the embedded procedural scenes, which render with the experiment's sensor.")
    image_size: int = Field(64, ge=8, le=4096, description="Side of the square images fed to the models, in pixels.")
    batch_size: int = Field(16, ge=1, le=65536, description="Images per optimisation step (per process).")
    num_workers: int = Field(0, ge=0, le=256, description="DataLoader worker processes (0 loads in the main process).")
    val_fraction: float = Field(0.1, ge=0.0, lt=1.0, description="Fraction of samples held out for evaluation.")


class TokenizerLossConfig(Section):
    """The tokenizer objective: L1 + VQ + perceptual + adversarial (VQGAN's, with its safeguards)."""

    l1_weight: float = Field(1.0, ge=0.0, le=100.0, description="Weight of the L1 reconstruction loss.")
    codebook_weight: float = Field(1.0, ge=0.0, le=100.0, description="Weight of the quantizer's loss.")
    perceptual: Literal["none", "effnet_lite0", "lpips"] = Field(
        "effnet_lite0", description="Perceptual loss: 'lpips' needs user-supplied AlexNet and head weights; "
                                    "'effnet_lite0' is an offline feature loss on a real ImageNet network (not LPIPS).")
    perceptual_weight: float = Field(0.1, ge=0.0, le=100.0, description="Weight of the perceptual loss.")
    perceptual_image_size: int = Field(96, ge=32, le=512,
                                       description="Side the images are resized to for the perceptual network.")
    lpips_backbone: str | None = Field(None, description="Path of alexnet-owt-7be5be79.pth (or VQTOUCH_LPIPS_BACKBONE).")
    lpips_heads: str | None = Field(None, description="Path of LPIPS v0.1 alex.pth heads (or VQTOUCH_LPIPS_HEADS).")
    adversarial_weight: float = Field(0.8, ge=0.0, le=100.0, description="Weight of the hinge GAN loss (times the "
                                                                         "adaptive weight); 0 disables it.")
    disc_start: int = Field(2000, ge=0, description="Step at which the discriminator starts (it is not trained before).")
    adaptive_weight_max: float = Field(1e4, gt=0.0, description="Upper clamp of the adaptive GAN weight.")


class TokenizerConfig(Section):
    """The tactile tokenizer: an autoencoder plugin plus a quantizer plugin, and how it is trained."""

    encoder: Slot("encoder") | None = Field(None, description="Autoencoder plugin (e.g. dm_vqgan, vqgan).")
    quantizer: Slot("quantizer") | None = Field(None, description="Quantizer plugin (e.g. vq, ema_vq).")
    discriminator: Slot("discriminator") | None = Field(
        None, description="Discriminator plugin for the adversarial loss (e.g. patchgan); null trains without one.")
    loss: TokenizerLossConfig = Field(default_factory=TokenizerLossConfig, description="Training objective.")


class TrainConfig(Section):
    """Optimisation settings shared by every training stage."""

    steps: int = Field(1000, ge=0, description="Optimisation steps for each trained stage.")
    learning_rate: float = Field(1e-4, gt=0, le=10, description="Peak learning rate.")
    weight_decay: float = Field(0.0, ge=0, le=1, description="Decoupled weight decay (AdamW).")
    grad_clip: float | None = Field(1.0, gt=0, description="Clip the gradient norm to this value; null disables.")
    precision: Literal["fp32", "bf16"] = Field(
        "fp32", description="Autocast precision of the networks; quantizer and diffusion maths stay fp32.")
    optimizer: Literal["adamw", "adam"] = Field("adamw", description="Optimizer of every trained module.")
    betas: tuple[float, float] = Field((0.5, 0.9), description="Adam betas (VQGAN uses (0.5, 0.9)).")
    ema_decay: float | None = Field(None, gt=0.0, lt=1.0,
                                    description="Keep an exponential moving average of the weights with this decay "
                                                "(saved next to the raw weights); null disables.")
    checkpoint_every: int = Field(500, ge=1, description="Write a checkpoint every this many steps.")
    log_every: int = Field(50, ge=1, description="Write metrics.jsonl every this many steps.")
    max_skipped_steps: int = Field(20, ge=1, description="Abort after this many consecutive steps with a non-finite "
                                                         "loss (each one is skipped and reported).")


class ExperimentConfig(Section):
    """One experiment: which stages run, which plugin fills each slot, and how to train.

    Every slot is a mapping ``{"name": <plugin>, ...options}``; only the slots needed by
    ``stages`` are built (see ``STAGE_SLOTS``).
    """

    schema_version: Literal[1] = Field(1, description="Version of this configuration schema.")
    name: str = Field("experiment", min_length=1, max_length=100, pattern=r"^[A-Za-z0-9._-]+$",
                      description="Experiment name, used in the run directory name.")
    scene: str | None = Field(None, description="Scene preset this config started from (informational).")
    description: str = Field("", description="Free text describing the experiment.")
    stages: list[Stage] = Field(default_factory=list, description="Pipeline stages this experiment runs, in order.")
    seed: int = Field(0, ge=0, lt=2**63, description="Seed for every random number generator.")
    deterministic: bool = Field(False, description="Ask PyTorch for deterministic algorithms (slower).")
    device: Literal["auto", "cpu", "cuda"] = Field("auto", description="Compute device; auto picks CUDA when present.")
    output_dir: str = Field("runs", min_length=1, description="Folder under which run directories are created.")
    sensor: Slot("sensor_family") | None = Field(None, description="Sensor family (and variant) of the training data.")
    target_sensor: Slot("sensor_family") | None = Field(
        None, description="Unseen sensor to adapt to (cross-sensor and few-shot scenes).")
    data: DataConfig = Field(default_factory=DataConfig, description="Data source and shapes.")
    tokenizer: TokenizerConfig = Field(default_factory=TokenizerConfig, description="Tactile tokenizer.")
    clusterer: Slot("clusterer") | None = Field(None, description="Sensor-family clustering plugin.")
    conditioner: Slot("conditioner") | None = Field(None, description="Condition encoder for the generator.")
    generator: Slot("generator") | None = Field(None, description="Generator over the code grid.")
    metrics: list[Slot("metric")] = Field(default_factory=list, description="Metrics reported by the evaluate stage.")
    train: TrainConfig = Field(default_factory=TrainConfig, description="Optimisation settings.")

    def slot(self, path: str) -> PluginConfig | list[PluginConfig] | None:
        """The config in slot ``path`` (e.g. ``"tokenizer.encoder"``)."""
        value: Any = self
        for part in path.split("."):
            value = getattr(value, part)
        return value

    def required_slots(self) -> list[str]:
        """Slot paths the configured stages need, in stage order without repeats."""
        seen: dict[str, None] = {}
        for stage in self.stages:
            for path in STAGE_SLOTS[stage]:
                seen.setdefault(path, None)
        return list(seen)

    def missing_slots(self) -> list[tuple[str, str]]:
        """(stage, slot) pairs that a stage needs but the config leaves empty (optional slots excepted)."""
        missing = []
        for stage in self.stages:
            for path in STAGE_SLOTS[stage]:
                if path in OPTIONAL_SLOTS:
                    continue
                value = self.slot(path)
                if value is None or value == []:
                    missing.append((stage, path))
        return missing

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-ready dict (plugin options included)."""
        return self.model_dump(mode="json")


# -- loading and merging --------------------------------------------------------------------

def load_config_file(path: str | Path) -> dict[str, Any]:
    """Read a TOML or JSON config file into a dict; errors name the file and the problem."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file {str(path)!r} does not exist")
    text = path.read_text(encoding="utf-8")
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
        if isinstance(current, dict) and isinstance(value, Mapping) and not _selects_other_plugin(current, value):
            merged[key] = merge_configs(current, value)
        else:
            merged[key] = copy.deepcopy(value)
    return merged


def _selects_other_plugin(current: Mapping[str, Any], update: Mapping[str, Any]) -> bool:
    return "name" in current and "name" in update and current["name"] != update["name"]


def parse_override(text: str) -> tuple[list[str], Any]:
    """Split ``a.b=value`` into its key path and value (JSON if it parses, else a string)."""
    key, sep, raw = text.partition("=")
    key = key.strip()
    if not sep or not key or any(not part for part in key.split(".")):
        raise ConfigError(f"bad override {text!r}: expected PATH=VALUE, e.g. --set train.steps=200")
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
            raise ConfigError(f"cannot set {'.'.join(path)}: {'.'.join(path[:depth + 1])} is "
                              f"{type(child).__name__} {child!r}, not a section")
        node = child
    last = path[-1]
    if isinstance(node, list):
        node[_list_index(last, node, path)] = value
    elif last == "name" and len(path) > 1 and "name" in node and node["name"] != value:
        node.clear()
        node["name"] = value
    elif isinstance(value, Mapping) and isinstance(node.get(last), dict) and not _selects_other_plugin(node[last], value):
        node[last] = merge_configs(node[last], value)
    else:
        node[last] = value
    return result


def _list_index(part: str, node: list[Any], where: Sequence[str]) -> int:
    if not part.isdigit() or int(part) >= len(node):
        raise ConfigError(f"cannot set {'.'.join(where)}: index {part!r} is not within a list of {len(node)}")
    return int(part)


def format_validation_error(exc: ValidationError, prefix: str = "") -> str:
    """One line per problem: the dotted path, what is wrong and the offending value."""
    problems = []
    for error in exc.errors(include_url=False):
        loc = ".".join(str(part) for part in (prefix, *error["loc"]) if part != "")
        message = error["msg"]
        if error["type"] not in {"unknown_plugin", "unknown_option", "missing_plugin_name", "missing"}:
            shown = repr(error.get("input"))
            message += f" (got {shown if len(shown) <= 60 else shown[:57] + '...'})"
        problems.append(f"{loc or '<root>'}: {message}")
    if len(problems) == 1:
        return f"invalid configuration: {problems[0]}"
    return f"invalid configuration ({len(problems)} problems): " + "; ".join(problems)


def validate_experiment(data: Mapping[str, Any], host: Any = None) -> ExperimentConfig:
    """Validate a raw dict into an :class:`ExperimentConfig` against ``host``'s registries.

    Afterwards every plugin's ``vqtouch_validate_experiment`` hook may veto the combination.
    """
    if host is None:
        from .plugin_manager import default_host

        host = default_host()
    try:
        config = ExperimentConfig.model_validate(dict(data), context={"host": host})
    except ValidationError as exc:
        raise ConfigError(format_validation_error(exc)) from None
    host.pm.hook.vqtouch_validate_experiment(config=config)
    return config


def resolve_config(scene: str | None = None, files: Iterable[str | Path] = (), overrides: Iterable[str] = (),
                   host: Any = None) -> ExperimentConfig:
    """Build the experiment config from a scene preset, config files and ``--set`` overrides."""
    if host is None:
        from .plugin_manager import default_host

        host = default_host()
    data: dict[str, Any] = {}
    if scene is not None:
        entry = host.scene(scene)
        data = merge_configs({"name": scene, "scene": scene, "description": entry.description}, entry.config)
    for path in files:
        data = merge_configs(data, load_config_file(path))
    applied: list[tuple[str, list[str]]] = []
    for text in overrides:
        key_path, value = parse_override(text)
        _refuse_lost_overrides(data, key_path, value, applied, text)
        data = apply_override(data, key_path, value)
        applied.append((text, key_path))
    return validate_experiment(data, host)


def _refuse_lost_overrides(data: dict[str, Any], path: list[str], value: Any,
                           applied: list[tuple[str, list[str]]], text: str) -> None:
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
        node = node.get(part) if isinstance(node, dict) else None
    if not isinstance(node, dict) or node.get("name") in (None, new_name):
        return
    depth = len(slot)
    lost = [earlier for earlier, earlier_path in applied
            if len(earlier_path) > depth and earlier_path[:depth] == slot and earlier_path[depth] != "name"]
    if lost:
        where = ".".join(slot)
        raise ConfigError(f"--set {text} selects another plugin for {where}, which resets its options and would "
                          f"drop the earlier {', '.join('--set ' + t for t in lost)}; put --set {text} before them")

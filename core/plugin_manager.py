"""Loading plugins and building components from them.

``load_plugins()`` returns a fresh :class:`PluginHost` (no import-time side effects):

1. hookspecs are added;
2. built-in plugins load: the entry points of the ``vqtouch`` distribution itself, group
   ``vqtouch``, i.e. exactly the mechanism third-party packages use;
3. third-party entry points (group ``vqtouch``) load unless autoload is off
   (``VQTOUCH_DISABLE_PLUGIN_AUTOLOAD=1`` or ``autoload=False``);
4. extra plugin modules load (``extra=`` or ``VQTOUCH_PLUGINS=pkg.mod,other.mod``);
5. ``check_pending()`` fails on any ``vqtouch_*`` function that matches no hook;
6. every registration hook runs, one plugin at a time so each entry knows its source
   (components, then stages, then scenes);
7. the registries are frozen and the experiment model is assembled from core's sections
   and every stage's own section; each stage's slot paths are checked against it.

There is no process-wide host: whoever validates a config, builds a component or loads a
checkpoint passes the host whose plugins to use (the CLI makes one per command).

Any plugin, built-in or not, can be blocked by name with ``block=`` or
``VQTOUCH_BLOCK_PLUGINS=name,other``.
"""

from __future__ import annotations

import importlib
import importlib.metadata as importlib_metadata
import os
import sys
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import pluggy
from pydantic import Field, ValidationError, create_model

from . import hookspecs
from .config import ExperimentConfig, Section, SlotInfo, slots_of
from .deprecations import HOOK_RENAMES, HOOKS_REMOVED, RENAMED_IN
from .errors import ConfigError, PluginError, UnknownPluginError, format_validation_error, unknown_name_message
from .plugin_config import PluginConfig
from .references import check_callable_or_reference
from .registry import PluginEntry, PluginSource, Registry
from .stages import StageEntry

if TYPE_CHECKING:
    from .components import BuildContext

ENTRY_POINT_GROUP = "vqtouch"
BUILTIN_DISTRIBUTION = "vqtouch"
ENV_DISABLE_AUTOLOAD = "VQTOUCH_DISABLE_PLUGIN_AUTOLOAD"
ENV_BLOCK = "VQTOUCH_BLOCK_PLUGINS"
ENV_EXTRA = "VQTOUCH_PLUGINS"
ENV_TRACE = "VQTOUCH_TRACE_PLUGINS"


@dataclass(frozen=True)
class RegistryKind:
    """A kind of component: its registry name, registration hook and interface.

    ``interface`` names the kind's base class in :mod:`vqtouch.core.components`, imported (with
    torch) only when a component is built or checked, so that loading plugins stays light.
    ``provides`` are the :class:`BuildContext` facts its components fix (see
    ``ProvidesContext``) and ``reads`` the facts its factories read, so the assembly builds
    providers first.
    """

    name: str
    hook: str
    description: str
    interface: str
    provides: tuple[str, ...] = ()
    reads: tuple[str, ...] = ()

    @property
    def base_type(self) -> type:
        """The kind's base class (imports :mod:`vqtouch.core.components`)."""
        from . import components

        return getattr(components, self.interface)


REGISTRY_KINDS: tuple[RegistryKind, ...] = (
    RegistryKind(
        "autoencoder",
        "vqtouch_register_autoencoders",
        "tokenizer autoencoders",
        "Autoencoder",
        provides=("latent_dim",),
    ),
    RegistryKind(
        "quantizer",
        "vqtouch_register_quantizers",
        "latent quantizers",
        "Quantizer",
        provides=("codebook_size",),
        reads=("latent_dim",),
    ),
    RegistryKind("discriminator", "vqtouch_register_discriminators", "GAN discriminators", "Discriminator"),
    RegistryKind(
        "conditioner",
        "vqtouch_register_conditioners",
        "condition encoders",
        "Conditioner",
        reads=("num_classes", "class_names"),
    ),
    RegistryKind("sensor_family", "vqtouch_register_sensor_families", "tactile sensor renderers", "SensorFamily"),
    RegistryKind(
        "generator",
        "vqtouch_register_generators",
        "code-grid generators",
        "Generator",
        reads=("codebook_size", "num_classes", "code_grid"),
    ),
    RegistryKind("sampler", "vqtouch_register_samplers", "discrete-diffusion samplers", "Sampler"),
    RegistryKind("best_of_ranker", "vqtouch_register_best_of_rankers", "best-of-K candidate rankers", "BestOfRanker"),
    RegistryKind("clusterer", "vqtouch_register_clusterers", "sensor-family clusterers", "Clusterer"),
    RegistryKind(
        "dataset",
        "vqtouch_register_datasets",
        "tactile dataset readers",
        "TactileDataset",
        provides=("num_classes", "class_names"),
    ),
    RegistryKind("metric", "vqtouch_register_metrics", "image metrics", "Metric"),
)
KINDS_BY_NAME = {kind.name: kind for kind in REGISTRY_KINDS}
KIND_NAMES = tuple(kind.name for kind in REGISTRY_KINDS)


@dataclass(frozen=True)
class SceneEntry:
    """A registered scene preset: a partial experiment config and its documentation."""

    name: str
    config: dict[str, Any]
    description: str
    source: PluginSource


@dataclass(frozen=True)
class ComponentSpec:
    """What a built component was made from; the checkpoint writer stores all of it."""

    kind: str
    config: PluginConfig
    context: BuildContext
    source: PluginSource


def _env_list(variable: str) -> list[str]:
    return [item.strip() for item in os.environ.get(variable, "").split(",") if item.strip()]


def _is_truthy(variable: str) -> bool:
    return os.environ.get(variable, "").strip().lower() in {"1", "true", "yes", "on"}


class PluginHost:
    """A loaded plugin manager with its registries, stages, scenes and experiment model.

    Make one with :func:`load_plugins` and pass it to whatever validates, builds or loads.
    """

    def __init__(self, pm: pluggy.PluginManager, sources: dict[str, PluginSource]) -> None:
        self.pm = pm
        self.sources = sources
        self.registries: dict[str, Registry] = {
            kind.name: Registry(kind.name, kind.description, lambda kind=kind: kind.base_type)
            for kind in REGISTRY_KINDS
        }
        self.stages: dict[str, StageEntry] = {}
        self.scenes: dict[str, SceneEntry] = {}
        #: The experiment config model: core's fields plus one section per stage that has one.
        self.experiment_model: type[ExperimentConfig] = ExperimentConfig
        #: Every slot of :attr:`experiment_model` by dotted path.
        self.slots: dict[str, SlotInfo] = slots_of(ExperimentConfig)

    # -- lookup ---------------------------------------------------------------------------
    def registry(self, kind: str) -> Registry:
        """The registry of one kind (``autoencoder``, ``conditioner``, ...)."""
        try:
            return self.registries[kind]
        except KeyError:
            raise UnknownPluginError(unknown_name_message("registry kind", kind, self.registries)) from None

    def stage(self, name: str) -> StageEntry:
        """A stage by name; unknown names list the registered stages."""
        try:
            return self.stages[name]
        except KeyError:
            raise UnknownPluginError(unknown_name_message("stage", name, self.stages)) from None

    def scene(self, name: str) -> SceneEntry:
        """A scene preset by name; unknown names list the registered scenes."""
        try:
            return self.scenes[name]
        except KeyError:
            raise UnknownPluginError(unknown_name_message("scene", name, self.scenes)) from None

    def entries(self) -> list[PluginEntry]:
        """Every registered component entry, grouped by kind."""
        return [entry for kind in KIND_NAMES for entry in self.registries[kind]]

    # -- building -------------------------------------------------------------------------
    def validate(self, kind: str, config: PluginConfig | dict[str, Any] | str) -> PluginConfig:
        """Validate raw options for ``kind`` into the plugin's config model (ConfigError on failure)."""
        try:
            return self.registry(kind).validate_config(config, context={"host": self})
        except ValidationError as exc:
            raise ConfigError(format_validation_error(exc, prefix=kind)) from None

    def build(
        self, kind: str, config: PluginConfig | dict[str, Any] | str, context: BuildContext | None = None, **inputs: Any
    ) -> Any:
        """Build one component of ``kind`` from its config, the experiment context and the built
        ``inputs`` its plugin declared (e.g. ``sensor=...`` for a dataset that renders).

        Inside an experiment use :class:`vqtouch.core.Assembly`, which supplies the inputs.
        """
        registry = self.registry(kind)
        config = self.validate(kind, config)
        if context is None:
            from .components import BuildContext

            context = BuildContext()
        entry = registry.get(config.name)
        missing = [name for name in entry.inputs if inputs.get(name) is None]
        if missing:
            raise ConfigError(
                f"{kind} {entry.name!r} needs {', '.join(missing)}: build it through the experiment's "
                f"Assembly (which supplies the experiment's {missing[0]}) or pass {missing[0]}=..."
            )
        extra = sorted(set(inputs) - set(entry.inputs) - set(entry.optional_inputs))
        if extra:
            raise PluginError(
                f"{kind} {entry.name!r} takes no input {extra[0]!r} (it declares "
                f"{list(entry.inputs + entry.optional_inputs)})"
            )
        component = entry.load_factory()(config, context, **inputs)
        if registry.base_type is not None and not isinstance(component, registry.base_type):
            raise PluginError(
                f"{entry.source.describe()}: factory of {kind} {entry.name!r} returned "
                f"{type(component).__name__}, which is not a vqtouch.core.{registry.base_type.__name__}"
            )
        object.__setattr__(component, "vqtouch_spec", ComponentSpec(kind, config, context, entry.source))
        return component

    # -- reporting ------------------------------------------------------------------------
    def describe(self) -> list[dict[str, Any]]:
        """One row per registered component and scene: kind, name, plugin, package, version."""
        rows = []
        for entry in self.entries():
            rows.append(
                {
                    "kind": entry.kind,
                    "name": entry.name,
                    "plugin": entry.source.plugin,
                    "package": entry.source.distribution,
                    "version": entry.source.version,
                    "description": entry.description,
                }
            )
        for stage in sorted(self.stages.values(), key=lambda s: s.name):
            rows.append(
                {
                    "kind": "stage",
                    "name": stage.name,
                    "plugin": stage.source.plugin,
                    "package": stage.source.distribution,
                    "version": stage.source.version,
                    "description": stage.description,
                }
            )
        for scene in sorted(self.scenes.values(), key=lambda s: s.name):
            rows.append(
                {
                    "kind": "scene",
                    "name": scene.name,
                    "plugin": scene.source.plugin,
                    "package": scene.source.distribution,
                    "version": scene.source.version,
                    "description": scene.description,
                }
            )
        return rows


def _source_for(plugin_name: str, module: Any, dist: importlib_metadata.Distribution | None) -> PluginSource:
    module_name = getattr(module, "__name__", type(module).__name__)
    if dist is not None:
        return PluginSource(plugin_name, module_name, dist.metadata["Name"], dist.version)
    return PluginSource(plugin_name, module_name, None, getattr(module, "__version__", None))


def _builtin(ep: importlib_metadata.EntryPoint) -> bool:
    dist = getattr(ep, "dist", None)
    return dist is not None and dist.metadata["Name"].lower().replace("_", "-") == BUILTIN_DISTRIBUTION


def load_plugins(
    *, autoload: bool | None = None, extra: Iterable[str | Any] = (), block: Iterable[str] = ()
) -> PluginHost:
    """Load built-in and third-party plugins into a fresh :class:`PluginHost`.

    ``autoload``: load third-party entry points (default: unless
    ``VQTOUCH_DISABLE_PLUGIN_AUTOLOAD`` is set).  ``extra``: plugin modules (dotted names
    or module objects) to load in addition.  ``block``: plugin names never to load.
    """
    if autoload is None:
        autoload = not _is_truthy(ENV_DISABLE_AUTOLOAD)
    blocked = set(block) | set(_env_list(ENV_BLOCK))

    pm = pluggy.PluginManager(hookspecs.PROJECT_NAME)
    pm.add_hookspecs(hookspecs)
    if _is_truthy(ENV_TRACE):
        pm.trace.root.setwriter(lambda message: sys.stderr.write(message))
        pm.enable_tracing()
    sources: dict[str, PluginSource] = {}

    entry_points = sorted(
        importlib_metadata.entry_points(group=ENTRY_POINT_GROUP), key=lambda ep: (not _builtin(ep), ep.name)
    )
    for ep in entry_points:
        if ep.name in blocked or (not autoload and not _builtin(ep)):
            continue
        if pm.get_plugin(ep.name) is not None:
            previous = sources[ep.name]
            raise PluginError(
                f"two plugins are named {ep.name!r}: {previous.describe()} and one from "
                f"{ep.dist.metadata['Name'] if ep.dist else ep.value}; block one with {ENV_BLOCK}={ep.name}"
            )
        dist = getattr(ep, "dist", None)
        try:
            module = ep.load()
        except Exception as exc:  # noqa: BLE001 - any import failure is reported the same way
            origin = f" from {dist.metadata['Name']} {dist.version}" if dist else ""
            raise PluginError(
                f"error loading plugin {ep.name!r}{origin}: {type(exc).__name__}: {exc}. "
                f"Block it with {ENV_BLOCK}={ep.name}"
            ) from exc
        pm.register(module, name=ep.name)
        sources[ep.name] = _source_for(ep.name, module, dist)

    for item in [*extra, *_env_list(ENV_EXTRA)]:
        if isinstance(item, str):
            name = item
            if name in blocked:
                continue
            try:
                module = importlib.import_module(item)
            except Exception as exc:  # noqa: BLE001
                raise PluginError(f"error loading plugin module {item!r}: {type(exc).__name__}: {exc}") from exc
        else:
            module = item
            name = getattr(item, "__name__", None) or f"plugin-{id(item)}"
        if name in blocked or pm.is_registered(module):
            continue
        pm.register(module, name=name)
        sources[name] = _source_for(name, module, None)

    _refuse_removed_hooks(pm, sources)
    try:
        pm.check_pending()
    except pluggy.PluginValidationError as exc:
        raise PluginError(f"{exc}; hook names must match a vqtouch_* hookspec (see vqtouch.core.hookspecs)") from None

    host = PluginHost(pm, sources)
    old_hooks = {new: old for old, new in HOOK_RENAMES.items()}
    for kind in REGISTRY_KINDS:
        _run_registration_hook(host, kind.hook, _component_register(host.registries[kind.name]))
        if kind.hook in old_hooks:  # 0.1.0 plugins still register (pluggy warned when they loaded)
            _run_registration_hook(host, old_hooks[kind.hook], _component_register(host.registries[kind.name]))
        host.registries[kind.name].freeze()
    _run_registration_hook(host, "vqtouch_register_stages", lambda source: _stage_register(host, source))
    _run_registration_hook(host, "vqtouch_register_scenes", lambda source: _scene_register(host, source))
    _assemble_experiment_model(host)
    return host


def _refuse_removed_hooks(pm: pluggy.PluginManager, sources: dict[str, PluginSource]) -> None:
    """PluginError naming the plugin, its distribution and the replacement when a plugin implements a
    hook that 0.2.0 removed (pluggy would only say the hook is unknown)."""
    for name, plugin in pm.list_name_plugin():
        for hook, replacement in HOOKS_REMOVED.items():
            if callable(getattr(plugin, hook, None)):
                raise PluginError(
                    f"{sources[name].describe()} implements {hook}, which vqtouch {RENAMED_IN} removed: "
                    f"{replacement}; update the plugin or block it with {ENV_BLOCK}={name}"
                )


def _assemble_experiment_model(host: PluginHost) -> None:
    """Core's ExperimentConfig plus one field per stage section; every stage's slot paths checked."""
    sections: dict[str, Any] = {}
    for stage in host.stages.values():
        if stage.section is None:
            continue
        if stage.name in ExperimentConfig.model_fields:
            raise PluginError(
                f"{stage.source.describe()} registered stage {stage.name!r}, whose section would "
                f"replace core's {stage.name!r} field; rename the stage"
            )
        sections[stage.name] = (
            stage.section,
            Field(default_factory=stage.section, description=stage.description or f"The {stage.name} stage."),
        )
    if sections:
        host.experiment_model = create_model(
            "ExperimentConfig",
            __base__=ExperimentConfig,
            __doc__=ExperimentConfig.__doc__,
            __module__=ExperimentConfig.__module__,
            **sections,
        )
    host.slots = slots_of(host.experiment_model)
    for stage in host.stages.values():
        for path in stage.slots:
            if path not in host.slots:
                raise PluginError(
                    f"{stage.source.describe()}: stage {stage.name!r} declares slot {path!r}, which "
                    f"the experiment config does not have; slots: {', '.join(host.slots)}"
                )


def _stage_register(host: PluginHost, source: PluginSource) -> Any:
    def register(
        name: str,
        run: Any,
        *,
        section: type[Section] | None = None,
        needs: Iterable[str] = (),
        uses: Iterable[str] = (),
        description: str = "",
        demo: Mapping[str, Any] | None = None,
        makes: Iterable[str] = (),
        trains: str | None = None,
    ) -> None:
        if name in host.stages:
            raise PluginError(
                f"duplicate stage {name!r}: registered by {host.stages[name].source.describe()} "
                f"and again by {source.describe()}; block one with {ENV_BLOCK}"
            )
        check_callable_or_reference(run, f"{source.describe()}: stage {name!r}'s run(job)")
        if section is not None and not (isinstance(section, type) and issubclass(section, Section)):
            raise PluginError(
                f"{source.describe()}: stage {name!r} section must subclass vqtouch.core.Section, got {section!r}"
            )
        makes = (makes,) if isinstance(makes, str) else tuple(makes)
        for product in makes:
            other = next((stage for stage in host.stages.values() if product in stage.makes), None)
            if other is not None:
                raise PluginError(
                    f"{source.describe()}: stage {name!r} makes product {product!r}, which stage "
                    f"{other.name!r} ({other.source.describe()}) already makes; a product has one "
                    "maker, so rename one"
                )
        if trains is not None and trains not in (demo or {}):
            raise PluginError(
                f"{source.describe()}: stage {name!r} trains {trains!r} but its demo caps do not name it; "
                f"add {trains!r} to demo= so the demo can say when it trained briefly"
            )
        host.stages[name] = StageEntry(
            name, run, section, tuple(needs), tuple(uses), description, source, dict(demo or {}), makes, trains
        )

    return register


def _run_registration_hook(host: PluginHost, hook_name: str, make_register: Any) -> None:
    """Call each implementation of a registration hook with a register bound to its plugin."""
    caller = getattr(host.pm.hook, hook_name)
    for impl in caller.get_hookimpls():  # registration order: built-ins first
        source = host.sources[impl.plugin_name]
        kwargs = {"register": make_register(source)} if "register" in impl.argnames else {}
        try:
            impl.function(**kwargs)
        except PluginError:
            raise
        except Exception as exc:  # noqa: BLE001
            raise PluginError(
                f"{source.describe()} failed in {hook_name}: {type(exc).__name__}: {exc}. "
                f"Block it with {ENV_BLOCK}={source.plugin}"
            ) from exc


def _component_register(registry: Registry) -> Any:
    def bind(source: PluginSource) -> Any:
        def register(
            name: str,
            factory: Any,
            config: type[PluginConfig],
            *,
            description: str = "",
            aliases: Iterable[str] = (),
            inputs: Iterable[str] = (),
            demo: Mapping[str, Any] | None = None,
            optional_inputs: Iterable[str] = (),
        ) -> None:
            registry.add(
                PluginEntry(
                    registry.kind,
                    name,
                    factory,
                    config,
                    description,
                    source,
                    tuple(aliases),
                    tuple(inputs),
                    dict(demo or {}),
                    tuple(optional_inputs),
                )
            )

        return register

    return bind


def _scene_register(host: PluginHost, source: PluginSource) -> Any:
    def register(name: str, config: dict[str, Any], *, description: str = "") -> None:
        if name in host.scenes:
            raise PluginError(
                f"duplicate scene {name!r}: registered by {host.scenes[name].source.describe()} "
                f"and again by {source.describe()}"
            )
        if not isinstance(config, dict):
            raise PluginError(f"{source.describe()}: scene {name!r} config must be a dict, got {type(config).__name__}")
        host.scenes[name] = SceneEntry(name, config, description, source)

    return register

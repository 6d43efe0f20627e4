"""Named registries of plugin components (autoencoders, quantizers, conditioners, ...).

A registry maps a short name to a :class:`PluginEntry`: the factory that builds the
component, the pydantic model of its options and the plugin that registered it.  Lookups
of unknown names fail listing what exists and the closest match (timm/open_clip style);
registering a name twice fails naming both sources (mmengine style).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

from .errors import PluginError, UnknownPluginError, unknown_name_message
from .plugin_config import PluginConfig, literal_name_of
from .references import check_callable_or_reference, resolve


@dataclass(frozen=True)
class PluginSource:
    """Where a registration came from: the pluggy plugin name and its distribution."""

    plugin: str
    module: str
    distribution: str | None = None
    version: str | None = None

    def describe(self) -> str:
        """Human-readable origin, e.g. ``plugin 'label' (vqtouch 0.1.0)``."""
        dist = f" ({self.distribution} {self.version})" if self.distribution else ""
        return f"plugin {self.plugin!r}{dist}"


@dataclass(frozen=True)
class PluginEntry:
    """One registered component: how to build it and how to validate its options."""

    kind: str
    name: str
    #: Builds the component: a callable, or a ``"package.module:attribute"`` reference to one that is
    #: imported at the first build (:mod:`vqtouch.core.references`), so loading plugins stays light.
    factory: Callable[..., Any] | str
    config_model: type[PluginConfig]
    description: str
    source: PluginSource
    aliases: tuple[str, ...] = ()
    #: Built components the factory takes as keyword arguments (e.g. ``("sensor",)``).
    inputs: tuple[str, ...] = ()
    #: Caps on this plugin's options for ``vqtouch demo`` (e.g. ``{"num_samples": 240}``).
    demo: Mapping[str, Any] = field(default_factory=dict)
    #: Built components the factory takes when the experiment has them (e.g. ``("paired_sensor",)``);
    #: absent ones are not passed, so the factory gives them a default.
    optional_inputs: tuple[str, ...] = ()

    def load_factory(self) -> Callable[..., Any]:
        """The factory itself (its module imported when it was registered as a reference)."""
        return resolve(self.factory, f"{self.source.describe()}: factory of {self.kind} {self.name!r}")


@dataclass
class Registry:
    """All entries of one kind (e.g. every autoencoder), keyed by name.

    ``base_type`` is the interface every built component must implement; it is checked
    when a component is built so that a plugin returning the wrong thing fails at once.  It may
    be given as a zero-argument callable returning the type, so that the registry exists before
    the interfaces' module (and torch) is imported.
    """

    kind: str
    description: str
    interface: type | Callable[[], type] | None = None
    _entries: dict[str, PluginEntry] = field(default_factory=dict)
    _aliases: dict[str, str] = field(default_factory=dict)
    _frozen: bool = False

    @property
    def base_type(self) -> type | None:
        """The interface every component of this kind implements (None: any object)."""
        if self.interface is None or isinstance(self.interface, type):
            return self.interface
        return self.interface()

    # -- registration -------------------------------------------------------------------
    def add(self, entry: PluginEntry) -> None:
        """Add an entry; duplicates (names or aliases) fail naming both registrants."""
        if self._frozen:
            raise PluginError(f"the {self.kind} registry is frozen; register plugins through hooks")
        if not isinstance(entry.config_model, type) or not issubclass(entry.config_model, PluginConfig):
            raise PluginError(
                f"{entry.source.describe()} registered {self.kind} {entry.name!r} with config "
                f"{entry.config_model!r}; it must be a subclass of vqtouch.core.PluginConfig"
            )
        declared = literal_name_of(entry.config_model)
        if declared != entry.name:
            raise PluginError(
                f"{entry.source.describe()} registered {self.kind} {entry.name!r} but its config "
                f"{entry.config_model.__name__} declares name {declared!r}; declare "
                f"`name: Literal[{entry.name!r}] = {entry.name!r}`"
            )
        check_callable_or_reference(entry.factory, f"{entry.source.describe()}: factory of {self.kind} {entry.name!r}")
        for key in (entry.name, *entry.aliases):
            existing = self._entries.get(key) or self._entries.get(self._aliases.get(key, ""))
            if existing is not None:
                raise PluginError(
                    f"duplicate {self.kind} name {key!r}: registered by {existing.source.describe()} "
                    f"and again by {entry.source.describe()}; block one with VQTOUCH_BLOCK_PLUGINS"
                )
        self._entries[entry.name] = entry
        for alias in entry.aliases:
            self._aliases[alias] = entry.name

    def freeze(self) -> None:
        """Refuse further registrations (called once every hook has run)."""
        self._frozen = True

    # -- lookup ---------------------------------------------------------------------------
    def names(self) -> list[str]:
        """Sorted canonical names of all entries."""
        return sorted(self._entries)

    def __contains__(self, name: object) -> bool:
        return name in self._entries or name in self._aliases

    def __iter__(self) -> Iterator[PluginEntry]:
        return iter(self._entries[name] for name in self.names())

    def __len__(self) -> int:
        return len(self._entries)

    def get(self, name: str) -> PluginEntry:
        """Return the entry for ``name`` (or an alias); unknown names list what exists."""
        canonical = self._aliases.get(name, name)
        try:
            return self._entries[canonical]
        except KeyError:
            raise UnknownPluginError(unknown_name_message(self.kind, name, self.names())) from None

    # -- configs --------------------------------------------------------------------------
    def validate_config(self, value: Any, context: dict[str, Any] | None = None) -> PluginConfig:
        """Validate a raw mapping (or a config object) into the plugin's own config model.

        ``context`` is passed to pydantic (it carries the host, for plugin configs that
        contain slots of their own).  Raises UnknownPluginError for names nobody
        registered and pydantic's ValidationError for bad options.
        """
        if isinstance(value, PluginConfig):
            value = value.model_dump()
        if isinstance(value, str):
            value = {"name": value}
        if isinstance(value, Mapping):
            value = dict(value)
        if not isinstance(value, dict) or "name" not in value:
            raise UnknownPluginError(
                f"a {self.kind} block needs a 'name' key choosing the plugin; available: "
                f"{', '.join(self.names()) or '(none installed)'}"
            )
        entry = self.get(str(value["name"]))
        # The name is already resolved, so validate against that plugin's model directly:
        # error paths then read like --set paths (conditioner.num_tokens, not conditioner.label.num_tokens).
        return entry.config_model.model_validate({**value, "name": entry.name}, context=context)

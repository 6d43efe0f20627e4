"""The one assembly path: an experiment's components, each built once, in dependency order.

The CLI, the demo, stages and tests all build through an :class:`Assembly`:

- it resolves the experiment's sensors in one place (``sensor``, and ``target_sensor`` or
  ``paired_sensor`` where a scene has two) and hands them to the factories that declared they
  need one (``inputs=("sensor",)``, e.g. the procedural dataset; ``optional_inputs=
  ("paired_sensor",)`` for a dataset that renders pairs when the experiment has a paired sensor);
- it keeps one :class:`BuildContext` and enriches it with the facts each built component
  fixes (classes, latent width, codebook size), building a fact's provider before any
  component whose kind reads it;
- it caches components by slot path, so a stage asking for ``data.dataset`` twice gets the
  same object, and a run builds only the slots its stages ask for.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Literal

from .components import BuildContext, SensorFamily
from .config import ExperimentConfig
from .deprecations import warn_renamed
from .errors import ConfigError
from .plugin_config import PluginConfig
from .plugin_manager import KINDS_BY_NAME
from .stages import empty_slot_reason, required_slots

if TYPE_CHECKING:
    from .plugin_manager import PluginHost


SensorRole = Literal["source", "target", "paired"]
SENSOR_SLOTS: dict[str, str] = {"source": "sensor", "target": "target_sensor", "paired": "paired_sensor"}


class Assembly:
    """Builds the components of one experiment for one host (see the module docstring)."""

    def __init__(self, config: ExperimentConfig, host: PluginHost, *, context: BuildContext | None = None) -> None:
        self.config = config
        self.host = host
        self.context = context or BuildContext(image_size=config.data.image_size)
        self._built: dict[str, Any] = {}

    # -- the experiment's sensors ----------------------------------------------------------------
    def sensor_config(self, role: SensorRole = "source") -> PluginConfig:
        """The config of the experiment's source or target sensor; ConfigError when it is not set."""
        path = SENSOR_SLOTS[role]
        value = self.config.slot(path)
        if value is None:
            raise ConfigError(f"this run {empty_slot_reason(path, self.host)}")
        return value

    def sensor(self, role: SensorRole = "source") -> SensorFamily:
        """The experiment's source (``sensor``) or target (``target_sensor``) sensor, built once."""
        return self.component(SENSOR_SLOTS[role])

    # -- components ------------------------------------------------------------------------------
    @property
    def built(self) -> dict[str, Any]:
        """The components built so far, by slot path (list slots map to lists)."""
        return dict(self._built)

    def component(self, path: str) -> Any:
        """The component in slot ``path`` (a list for list slots), built on first use.

        An empty slot raises ConfigError naming the slot and the plugins that could fill it.
        """
        if path in self._built:
            return self._built[path]
        info = self._slot_info(path)
        value = self.config.slot(path)
        if value is None:
            raise ConfigError(f"this run {empty_slot_reason(path, self.host)}")
        self._build_fact_providers(info.kind)
        if info.many:
            built: Any = [self.build(info.kind, item) for item in value]
        else:
            built = self.build(info.kind, value)
        self._built[path] = built
        return built

    def build(
        self, kind: str, config: PluginConfig | dict[str, Any] | str, *, sensor_role: SensorRole = "source"
    ) -> Any:
        """Build one (uncached) component of ``kind`` in this experiment's context: the inputs its
        plugin declares are supplied (``sensor``: the experiment's ``sensor_role`` sensor) and the
        facts it fixes are added to the context."""
        config = self.host.validate(kind, config)
        entry = self.host.registry(kind).get(config.name)
        inputs = {name: self._input(name, sensor_role) for name in entry.inputs}
        for name in entry.optional_inputs:
            if (value := self._optional_input(name)) is not None:
                inputs[name] = value
        component = self.host.build(kind, config, self.context, **inputs)
        facts = component.context_facts() if hasattr(component, "context_facts") else {}
        if facts:
            self.context = self.context.model_copy(update=facts)
        return component

    def dataset(
        self, config: PluginConfig | dict[str, Any] | None = None, *, sensor_role: SensorRole = "source"
    ) -> Any:
        """A dataset other than ``data.dataset`` (e.g. a common held-out set, or the same scenes
        rendered by the target sensor), built in this experiment's context; not cached."""
        if config is None:
            config = self.config.slot("data.dataset")
            if config is None:
                self.component("data.dataset")  # raises the standard empty-slot error
        return self.build("dataset", config, sensor_role=sensor_role)

    def build_slots(self, paths: list[str]) -> dict[str, Any]:
        """Build (or fetch) each configured slot of ``paths``; empty ones are skipped."""
        return {path: self.component(path) for path in paths if self.config.slot(path) not in (None, [])}

    # -- internals -------------------------------------------------------------------------------
    def _slot_info(self, path: str) -> Any:
        try:
            return self.host.slots[path]
        except KeyError:
            raise ConfigError(
                f"{path!r} is not a slot of this experiment config; slots: {', '.join(self.host.slots)}"
            ) from None

    def _input(self, name: str, sensor_role: SensorRole) -> Any:
        if name == "sensor":
            return self.sensor(sensor_role)
        raise ConfigError(f"no component can be supplied for input {name!r}; the assembly supplies: sensor")

    def _optional_input(self, name: str) -> Any:
        """An optional input: the experiment's paired sensor when it has one, else None."""
        if name == "paired_sensor":
            return self.sensor("paired") if self.config.paired_sensor is not None else None
        raise ConfigError(
            f"no component can be supplied for optional input {name!r}; the assembly supplies: paired_sensor"
        )

    def _build_fact_providers(self, kind: str) -> None:
        """Build the configured slots whose kind provides a fact ``kind`` reads (data before models)."""
        for fact in KINDS_BY_NAME[kind].reads:
            for path, info in self.host.slots.items():
                if (
                    fact in KINDS_BY_NAME[info.kind].provides
                    and path not in self._built
                    and not info.many
                    and self.config.slot(path) is not None
                ):
                    self.component(path)
                    break


def build_components(
    config: ExperimentConfig, host: PluginHost, *, slots: list[str] | None = None, context: BuildContext | None = None
) -> dict[str, Any]:
    """Deprecated (0.1.0): ``Assembly(config, host, context=context).build_slots(slots)``.

    ``slots`` defaults to every slot the config's stages need or use, as it did."""
    warn_renamed("build_components(config, host)", "Assembly(config, host).build_slots(paths)", what="function")
    assembly = Assembly(config, host, context=context)
    if slots is None:
        slots = required_slots(config, host)
    return assembly.build_slots(list(slots))

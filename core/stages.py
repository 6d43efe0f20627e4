"""Pipeline stages: a registry kind like the others, owned by plugins.

A stage plugin registers, through ``vqtouch_register_stages``::

    register("tokenizer", run_tokenizer_stage, section=TokenizerSection,
             needs=("data.dataset", "tokenizer.autoencoder", "tokenizer.quantizer"),
             uses=("tokenizer.discriminator", "metrics"), makes=("tokenizer",),
             description="Train the tactile tokenizer ...", demo={"train.steps": 40})

- ``section``: the stage's own config model (a :class:`~vqtouch.core.config.Section`),
  validated at ``config.<stage name>``; it holds the stage's slots and options, its
  optimiser settings included.  ``None`` for stages without options.
- ``needs``: slot paths the stage cannot run without; ``uses``: slots it uses when set.
  Both may name slots of any section (core's ``sensor``, ``data.dataset``, ``metrics``, or
  another stage's).  Unknown paths fail when plugins load.
- ``makes``: the products the stage publishes in its run (``job.publish(name, path, **facts)``)
  for later stages and commands, which ask the run for them (``job.product(name)``,
  ``RunDir.product``) instead of importing the stage's code.  A product name belongs to one stage.
- ``run(job)`` does the work and returns a JSON-ready report (scores; ``"picture"``: a file
  name inside the run, ``"caption"``: what its rows and columns show; ``"skipped"``: what could
  not be scored and why), or raises :class:`StageUnavailable` saying why it cannot run.
- ``demo``: caps applied to the section's options by ``vqtouch demo`` (paths inside the
  section), so the demo runs in minutes on a CPU.

Scenes list stages by name; an unknown stage fails listing what exists.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from .errors import PluginError, VqtouchError
from .references import resolve

if TYPE_CHECKING:
    from .assembly import Assembly
    from .config import ExperimentConfig, Section
    from .plugin_manager import PluginHost
    from .registry import PluginSource


class StageRun(Protocol):
    """What a stage uses of the run folder it works in (the runtime package's ``RunDir``
    implements it): its path and checkpoints folder, resuming a trainer, writing a record, and its products."""

    path: Path
    checkpoints: Path

    def resume(self, trainer: Any, host: PluginHost, **where: Any) -> Any: ...

    def write_json(self, name: str, data: Any) -> Path: ...

    def publish(self, name: str, path: str | Path, *, stage: str, **facts: Any) -> Any: ...

    def product(self, name: str, host: PluginHost | None = None) -> Any: ...


class StageUnavailable(VqtouchError):
    """A stage cannot run for this experiment; the message says why and what would fix it."""


@dataclass(frozen=True)
class StageEntry:
    """A registered stage: its config section, the slots it needs and how it runs."""

    name: str
    #: Does the stage's work: a callable, or a ``"package.module:attribute"`` reference to one,
    #: imported when the stage first runs (:mod:`vqtouch.core.references`).
    run: Callable[[StageJob], dict[str, Any] | None] | str
    section: type[Section] | None
    needs: tuple[str, ...]
    uses: tuple[str, ...]
    description: str
    source: PluginSource
    demo: Mapping[str, Any] = field(default_factory=dict)
    makes: tuple[str, ...] = ()
    #: The section option that holds how long the stage trains (``"train.steps"``), for a stage
    #: that trains a model: a run whose value is within the stage's demo cap is marked as briefly
    #: trained in the demo's report.
    trains: str | None = None

    def load_run(self) -> Callable[[StageJob], dict[str, Any] | None]:
        """The stage's ``run`` itself (its module imported when it was registered as a reference)."""
        return resolve(self.run, f"{self.source.describe()}: stage {self.name!r}'s run(job)")

    @property
    def slots(self) -> tuple[str, ...]:
        """Every slot the stage builds: needed ones first, then optional ones."""
        return self.needs + tuple(path for path in self.uses if path not in self.needs)


@dataclass
class StageJob:
    """Everything a stage's ``run`` receives.

    ``assembly`` builds (once) every component of the experiment; ``section`` is the stage's
    own validated config section (``config.<stage>``), None for stages without one;
    ``resume`` asks a training stage to continue from the run's latest checkpoint.
    """

    stage: str
    config: ExperimentConfig
    host: PluginHost
    run: StageRun
    assembly: Assembly
    section: Any = None
    resume: bool = False

    def publish(self, name: str, path: str | Path, **facts: Any) -> Any:
        """Publish what this stage made at ``path`` (inside the run) as product ``name``, one of
        the names its registration declares in ``makes``."""
        makes = self.host.stage(self.stage).makes
        if name not in makes:
            declared = ", ".join(makes) or "none"
            raise PluginError(
                f"{self.host.stage(self.stage).source.describe()}: stage {self.stage!r} published "
                f"{name!r} but declares makes={declared}; add it to the stage's registration"
            )
        return self.run.publish(name, path, stage=self.stage, **facts)

    def product(self, name: str) -> Any:
        """The product ``name`` an earlier stage published in this run (MissingProductError
        naming the stage that makes it when the run holds none)."""
        return self.run.product(name, self.host)


def required_slots(config: ExperimentConfig, host: PluginHost) -> list[str]:
    """Slot paths the configured stages build (needed and used ones), in stage order without repeats."""
    seen: dict[str, None] = {}
    for stage in config.stages:
        for path in host.stage(stage).slots:
            seen.setdefault(path, None)
    return list(seen)


def missing_slots(config: ExperimentConfig, host: PluginHost) -> list[tuple[str, str]]:
    """(stage, slot) pairs that a stage needs but the config leaves empty."""
    missing = []
    for stage in config.stages:
        for path in host.stage(stage).needs:
            value = config.slot(path)
            if value is None or value == []:
                missing.append((stage, path))
    return missing


def empty_slot_reason(path: str, host: PluginHost) -> str:
    """Why an empty required slot blocks a stage, with the choices that would fill it."""
    info = host.slots[path]
    names = host.registry(info.kind).names()
    if not names:
        return f"needs {path}, and no {info.kind} plugin is installed"
    how = f'--set {path}=\'[{{"name": "{names[0]}"}}]\'' if info.many else f"--set {path}.name=<{'|'.join(names)}>"
    return f"needs {path}, which the config leaves empty; choose with {how}"


def unavailable_reason(stage: str, config: ExperimentConfig, host: PluginHost) -> str | None:
    """Why ``stage`` cannot run with ``config`` before trying (empty needed slots), or None."""
    for missing_stage, path in missing_slots(config, host):
        if missing_stage == stage:
            return empty_slot_reason(path, host)
    return None

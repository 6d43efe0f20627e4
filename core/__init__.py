"""vqtouch core: registries, plugin loading, configs, stages, assembly, checkpoints, trainer and CLI.

The core knows no particular model, loss or stage.  Models, conditioners, sensor families,
metrics, stages and scenes are plugins, registered through the hooks in
:mod:`vqtouch.core.hookspecs`.

Typical use::

    from vqtouch.core import Assembly, load, load_plugins, resolve_config, save

    host = load_plugins()
    config = resolve_config("label-to-touch", host=host)
    assembly = Assembly(config, host)
    conditioners = assembly.component("generator.conditioners")
    save(conditioners[0], "label.safetensors", step=0, host=host)
    conditioner = load("label.safetensors", host=host)
"""

from __future__ import annotations

import importlib.metadata as _metadata
from typing import Any

from .assembly import Assembly, build_components  # noqa: F401 - the 0.1.0 name; warns when called
from .checkpoint import atomic_write, load, read_metadata, save
from .components import (
    Autoencoder,
    BuildContext,
    Clusterer,
    Conditioner,
    ConditionTokens,
    Discriminator,
    Generator,
    Metric,
    MetricSet,
    PerImageMetric,
    ProvidesContext,
    Quantizer,
    QuantizerOutput,
    Sampler,
    SensorFamily,
    SkippedMetric,
    TactileDataset,
    load_missing_as_zeros,
)
from .deprecations import warn_renamed
from .config import ExperimentConfig, Section, Slot, load_config_file, resolve_config, validate_experiment
from .errors import (
    CheckpointError,
    ConfigError,
    DatasetError,
    MissingWeightsError,
    PluginError,
    UnknownPluginError,
    VqtouchDeprecationWarning,
    VqtouchError,
    VqtouchWarning,
)
from .frozen import FrozenModule
from .hookspecs import hookimpl
from .plugin_config import PluginConfig
from .plugin_manager import PluginHost, load_plugins
from .runs import RunDir
from .seeding import make_generator, resolve_device, seed_everything
from .stages import StageJob, StageOutcome, StageUnavailable, required_slots, run_stage
from .training import TrainConfig
from .weights import WeightsSpec, resolve_weights

#: Names of 0.1.0 that still work, with a deprecation warning: old name -> (new name, object).
_RENAMED = {"Encoder": ("Autoencoder", Autoencoder)}


def __getattr__(name: str) -> Any:
    if name in _RENAMED:
        new, value = _RENAMED[name]
        warn_renamed(f"vqtouch.core.{name}", f"vqtouch.core.{new}")
        return value
    raise AttributeError(f"module 'vqtouch.core' has no attribute {name!r}")


try:
    __version__ = _metadata.version("vqtouch")
except _metadata.PackageNotFoundError:  # running from an uninstalled checkout
    __version__ = "0+unknown"

#: The author-facing API: what a plugin package or a script needs, covered by the versioning promise
#: in CHANGELOG.md.  The other names imported above stay importable from here for the built-ins and
#: for code written against 0.1.0, but are internal: import them from their modules (e.g.
#: ``vqtouch.core.runs.RunDir``) and expect them to move between minor releases.
__all__ = [
    # plugins: hooks, loading, options
    "hookimpl",
    "load_plugins",
    "PluginHost",
    "PluginConfig",
    "BuildContext",
    # the contracts a plugin implements
    "SensorFamily",
    "TactileDataset",
    "Autoencoder",
    "Quantizer",
    "QuantizerOutput",
    "Discriminator",
    "Conditioner",
    "ConditionTokens",
    "Generator",
    "Sampler",
    "Clusterer",
    "Metric",
    # stages
    "Section",
    "Slot",
    "StageJob",
    "StageUnavailable",
    # errors a plugin raises
    "VqtouchError",
    "ConfigError",
    "MissingWeightsError",
    # checkpoints
    "save",
    "load",
    "__version__",
]

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
from .components import (Autoencoder, BuildContext, Clusterer, Conditioner, ConditionTokens, Discriminator, Generator,
                         Metric, MetricSet, PerImageMetric, ProvidesContext, Quantizer, QuantizerOutput, Sampler, SensorFamily,
                         SkippedMetric, TactileDataset, load_missing_as_zeros)
from .deprecations import warn_renamed
from .config import ExperimentConfig, Section, Slot, load_config_file, resolve_config, validate_experiment
from .errors import (CheckpointError, ConfigError, DatasetError, MissingWeightsError, PluginError, UnknownPluginError,
                     VqtouchDeprecationWarning, VqtouchError, VqtouchWarning)
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

__all__ = [
    "Assembly", "Autoencoder", "BuildContext", "CheckpointError", "Clusterer", "ConditionTokens", "Conditioner",
    "ConfigError", "DatasetError", "Discriminator", "ExperimentConfig", "FrozenModule", "Generator", "Metric", "MetricSet",
    "MissingWeightsError", "PerImageMetric", "PluginConfig", "PluginError", "PluginHost", "ProvidesContext",
    "Quantizer", "QuantizerOutput", "RunDir", "Sampler", "Section", "SensorFamily", "SkippedMetric", "Slot", "StageJob", "StageOutcome",
    "StageUnavailable", "TactileDataset", "TrainConfig", "UnknownPluginError", "VqtouchDeprecationWarning", "VqtouchError", "VqtouchWarning", "WeightsSpec",
    "__version__", "atomic_write", "hookimpl", "load", "load_config_file", "load_missing_as_zeros", "load_plugins", "make_generator",
    "read_metadata", "required_slots", "resolve_config", "resolve_device", "resolve_weights", "run_stage", "save",
    "seed_everything", "validate_experiment",
]

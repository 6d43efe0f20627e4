"""vqtouch core: registries, plugin loading, configs, checkpoints and the CLI.

The core knows no particular model.  Models, conditioners, sensor families, metrics and
scenes are plugins, registered through the hooks in :mod:`vqtouch.core.hookspecs`.

Typical use::

    from vqtouch.core import load_plugins, resolve_config, build_components, save, load

    host = load_plugins()
    config = resolve_config("label-to-touch", overrides=["conditioner.num_classes=12"], host=host)
    components = build_components(config, host, slots=["conditioner"])
    save(components["conditioner"], "label.safetensors", step=0)
    conditioner = load("label.safetensors", host=host)
"""

from __future__ import annotations

import importlib.metadata as _metadata

from .assembly import build_components, build_context
from .checkpoint import atomic_write, load, read_metadata, save
from .components import (BuildContext, Clusterer, Conditioner, ConditionTokens, Discriminator, Encoder, Generator, Metric,
                         PerImageMetric, Quantizer, QuantizerOutput, SensorFamily, TactileDataset)
from .config import STAGE_SLOTS, ExperimentConfig, Slot, load_config_file, resolve_config, validate_experiment
from .errors import (CheckpointError, ConfigError, DatasetError, MissingWeightsError, PluginError, UnknownPluginError,
                     VqtouchError)
from .hookspecs import hookimpl
from .plugin_config import PluginConfig
from .plugin_manager import PluginHost, current_host, default_host, load_plugins, reset_default_host
from .runs import RunDir
from .seeding import make_generator, resolve_device, seed_everything
from .weights import WeightsSpec, resolve_weights

try:
    __version__ = _metadata.version("vqtouch")
except _metadata.PackageNotFoundError:  # running from an uninstalled checkout
    __version__ = "0+unknown"

__all__ = [
    "BuildContext", "CheckpointError", "DatasetError", "Clusterer", "ConditionTokens", "Conditioner", "ConfigError", "Discriminator", "Encoder",
    "ExperimentConfig", "Generator", "Metric", "MissingWeightsError", "PerImageMetric", "PluginConfig",
    "PluginError", "PluginHost", "Quantizer", "QuantizerOutput", "RunDir", "STAGE_SLOTS", "SensorFamily", "Slot", "TactileDataset",
    "UnknownPluginError", "VqtouchError", "WeightsSpec", "__version__", "atomic_write", "build_components",
    "build_context", "current_host", "default_host", "hookimpl", "load", "load_config_file", "load_plugins", "make_generator",
    "read_metadata", "reset_default_host", "resolve_config", "resolve_device", "resolve_weights", "save",
    "seed_everything", "validate_experiment",
]

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

import importlib
import importlib.metadata as _metadata
from typing import Any

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
from .hookspecs import hookimpl
from .plugin_config import PluginConfig
from .plugin_manager import PluginHost, load_plugins
from .seeding import resolve_device, seed_everything, make_generator
from .stages import StageJob, StageOutcome, StageUnavailable, required_slots, run_stage
from .train_config import TrainConfig
from .weights import WeightsSpec, resolve_weights

#: Names importable from here whose modules need torch: imported on first use (PEP 562), so that
#: ``import vqtouch.core`` (what every plugin module does) stays light.  Name -> its module.
_LAZY = {
    "Assembly": "assembly",
    "build_components": "assembly",
    "atomic_write": "checkpoint",
    "load": "checkpoint",
    "read_metadata": "checkpoint",
    "save": "checkpoint",
    **dict.fromkeys(
        (
            "Autoencoder",
            "BuildContext",
            "Clusterer",
            "Conditioner",
            "ConditionTokens",
            "Discriminator",
            "Generator",
            "Metric",
            "MetricSet",
            "PerImageMetric",
            "ProvidesContext",
            "Quantizer",
            "QuantizerOutput",
            "Sampler",
            "SensorFamily",
            "SkippedMetric",
            "TactileDataset",
            "load_missing_as_zeros",
        ),
        "components",
    ),
    "FrozenModule": "frozen",
    "RunDir": "runs",
}

#: Names of 0.1.0 that still work, with a deprecation warning: old name -> new name.
_RENAMED = {"Encoder": "Autoencoder"}


def __getattr__(name: str) -> Any:
    if name in _RENAMED:
        warn_renamed(f"vqtouch.core.{name}", f"vqtouch.core.{_RENAMED[name]}")
        return __getattr__(_RENAMED[name])
    if name in _LAZY:
        value = getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
        globals()[name] = value  # the next lookup finds it without this function
        return value
    raise AttributeError(f"module 'vqtouch.core' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *_LAZY, *_RENAMED})


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

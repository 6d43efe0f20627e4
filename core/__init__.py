"""vqtouch core: contracts, registries, hookspecs, configs, stages, assembly, checkpoints, errors and deprecations.

The core knows no particular model, loss or stage, and holds no machinery: the trainer, runs, the
CLI, the contract-test kit and the utilities are packages under :mod:`vqtouch.plugins`.  Models,
conditioners, sensor families, metrics, stages and scenes are plugins, registered through the
hooks in :mod:`vqtouch.core.hookspecs`.

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

from .deprecations import install_moved_modules, warn_moved, warn_renamed
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
from .stages import StageJob, StageUnavailable, required_slots

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
            "BestOfBatch",
            "BestOfRanker",
            "BuildContext",
            "Clusterer",
            "Conditioner",
            "ConditionTokens",
            "Discriminator",
            "Generator",
            "Metric",
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
}

#: Names of 0.1.0 whose modules left the core: they still import from here, with a deprecation
#: warning.  Name -> its module now.
_MOVED = {
    "TrainConfig": "vqtouch.plugins.training.settings",
    "WeightsSpec": "vqtouch.plugins.utils.weights",
    "resolve_weights": "vqtouch.plugins.utils.weights",
    "FrozenModule": "vqtouch.plugins.utils.frozen",
    "RunDir": "vqtouch.plugins.runtime.run_dir",
    "MetricSet": "vqtouch.plugins.evaluation.metric_set",
    "run_stage": "vqtouch.plugins.runtime.execution",
    "StageOutcome": "vqtouch.plugins.runtime.execution",
    **dict.fromkeys(("resolve_device", "seed_everything", "make_generator"), "vqtouch.plugins.utils.seeding"),
}
install_moved_modules()

#: Names of 0.1.0 that still work, with a deprecation warning: old name -> new name.
_RENAMED = {"Encoder": "Autoencoder"}


def __getattr__(name: str) -> Any:
    if name in _RENAMED:
        warn_renamed(f"vqtouch.core.{name}", f"vqtouch.core.{_RENAMED[name]}")
        return __getattr__(_RENAMED[name])
    if name in _MOVED:
        warn_moved(f"vqtouch.core.{name}", (f"{_MOVED[name]}.{name}",), what="name")
        return getattr(importlib.import_module(_MOVED[name]), name)
    if name in _LAZY:
        value = getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
        globals()[name] = value  # the next lookup finds it without this function
        return value
    raise AttributeError(f"module 'vqtouch.core' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *_LAZY, *_RENAMED, *_MOVED})


try:
    __version__ = _metadata.version("vqtouch")
except _metadata.PackageNotFoundError:  # running from an uninstalled checkout
    __version__ = "0+unknown"

#: The author-facing API: what a plugin package or a script needs, covered by the versioning promise
#: in CHANGELOG.md.  The other names imported above stay importable from here for the built-ins and
#: for code written against 0.1.0, but are internal: import them from their modules (e.g.
#: ``vqtouch.core.assembly.Assembly``) and expect them to move between minor releases.
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
    "BestOfRanker",
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

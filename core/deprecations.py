"""What changed in the plugin API and the config schema since vqtouch 0.1.0, in one place.

Each rename either keeps working with a one-line :class:`VqtouchDeprecationWarning` naming the new
name (the old spelling is removed in :data:`REMOVAL_VERSION`), or fails at load time with a one-line
error naming what replaced it.  Nothing that changed is left to fail later with a traceback.

- **config keys** (:data:`CONFIG_RENAMES`, :data:`CONFIG_REMOVED`, :data:`STAGES_REMOVED`): applied by
  :func:`vqtouch.core.config.migrate_config` to every configuration before it is validated (scenes, files, ``--set``
  and the ``config.json`` of old runs);
- **registry kinds** (:data:`KIND_RENAMES`): checkpoints whose header names an old kind load under
  the new one (:func:`current_kind`);
- **hooks** (:data:`HOOK_RENAMES`, :data:`HOOKS_REMOVED`): an old registration hook still registers,
  a removed one is refused when plugins load, naming the plugin;
- **modules** (:data:`MOVED_MODULES`): the trainer, runs, the CLI, the contract-test kit and the
  utilities left the core for packages under ``vqtouch.plugins``; their old import paths still
  import, with a warning (:func:`install_moved_modules`);
- **Python names**: ``Conditioner.modality`` (now ``sample_key``), ``vqtouch.core.Encoder`` (now
  ``Autoencoder``), ``build_components`` (now :class:`~vqtouch.core.Assembly`): their shims sit
  beside the new names and call :func:`warn_renamed`.  ``load`` without ``host`` is refused (there
  is no hidden plugin host).

The list is the CHANGELOG's "Renamed" section in code; a test checks that every entry is described
there.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import sys
import types
import warnings
from dataclasses import dataclass
from typing import Any

from .errors import VqtouchDeprecationWarning

#: The release that made the renames below.
RENAMED_IN = "0.2.0"
#: The release that will drop the old spellings that still work.
REMOVAL_VERSION = "0.3.0"


def warn_renamed(old: str, new: str, *, what: str = "name", stacklevel: int = 3) -> None:
    """One-line :class:`VqtouchDeprecationWarning`: ``old`` was renamed ``new`` in 0.2.0."""
    warnings.warn(
        f"{what} {old!r} was renamed to {new!r} in vqtouch {RENAMED_IN}; use {new!r} "
        f"('{old}' stops working in {REMOVAL_VERSION})",
        VqtouchDeprecationWarning,
        stacklevel=stacklevel,
    )


@dataclass(frozen=True)
class ConfigRename:
    """A config key that moved: ``old`` and ``new`` are dotted paths from the top of the config.

    ``as_list``: the new key holds a list of what the old one held (one conditioner became a list
    of them).  ``only_plugin_block``: move the old value only when it is a plugin block (a mapping
    with a ``name``), i.e. when the path now names a section that holds the block one level down.
    """

    old: str
    new: str
    as_list: bool = False
    only_plugin_block: bool = False


#: Config keys of 0.1.0 that still work (with a warning), in the order they are applied.
CONFIG_RENAMES: tuple[ConfigRename, ...] = (
    ConfigRename("tokenizer.encoder", "tokenizer.autoencoder"),
    ConfigRename("clusterer", "cluster.clusterer"),
    ConfigRename("generator", "generator.model", only_plugin_block=True),
    ConfigRename("conditioner", "generator.conditioners", as_list=True),
)

#: Config keys of 0.1.0 with no single new home: refused in one line that says where they went.
CONFIG_REMOVED: dict[str, str] = {
    "train": (
        "was split into tokenizer.train and generator.train (each stage trains with its own settings); "
        "move its options under the stage they were meant for, e.g. --set tokenizer.train.steps=200"
    ),
}

#: Stage names of 0.1.0 that are gone, and what replaced them.
STAGES_REMOVED: dict[str, str] = {
    "evaluate": (
        "each stage now scores its own product, and `vqtouch evaluate reconstruction|generation` "
        "scores a finished run; remove 'evaluate' from stages"
    ),
}

#: Registry kinds of 0.1.0 (checkpoint headers' ``vqtouch.component``) and their new names.
KIND_RENAMES: dict[str, str] = {"encoder": "autoencoder"}

#: Registration hooks of 0.1.0 that still work, and their new names.
HOOK_RENAMES: dict[str, str] = {"vqtouch_register_encoders": "vqtouch_register_autoencoders"}
#: Hooks of 0.1.0 that are gone, and what replaced them.
HOOKS_REMOVED: dict[str, str] = {
    "vqtouch_run_stage": (
        "stages are registered with vqtouch_register_stages(register) and run as run(job) (see docs/extending.md)"
    ),
}


def current_kind(kind: str) -> str:
    """The registry kind ``kind`` is called now (warning when a checkpoint used the 0.1.0 name)."""
    new = KIND_RENAMES.get(kind)
    if new is None:
        return kind
    warn_renamed(kind, new, what="component kind", stacklevel=3)
    return new


#: Core modules of 0.1.0 that moved out of the core, and where their names live now (the first
#: module holding a name serves it).
MOVED_MODULES: dict[str, tuple[str, ...]] = {
    "vqtouch.core.training": (
        "vqtouch.plugins.training.trainer",
        "vqtouch.plugins.training.trainer_state",
        "vqtouch.plugins.training.optimizers",
        "vqtouch.plugins.training.checkpoints",
        "vqtouch.plugins.training.precision",
        "vqtouch.plugins.training.settings",
        "vqtouch.plugins.training.batches",
        "vqtouch.plugins.training.processes",
    ),
    "vqtouch.core.train_config": ("vqtouch.plugins.training.settings",),
    "vqtouch.core.testing": ("vqtouch.plugins.testing",),
    "vqtouch.core.runs": (
        "vqtouch.plugins.runtime.run_dir",
        "vqtouch.plugins.runtime.records",
        "vqtouch.plugins.runtime.interruptions",
    ),
    "vqtouch.core.outputs": ("vqtouch.plugins.runtime.outputs",),
    "vqtouch.core.progress": ("vqtouch.plugins.utils.progress",),
    "vqtouch.core.images": ("vqtouch.plugins.utils.images",),
    "vqtouch.core.image_options": ("vqtouch.plugins.utils.image_options",),
    "vqtouch.core.data": ("vqtouch.plugins.utils.splits",),
    "vqtouch.core.weights": ("vqtouch.plugins.utils.weights",),
    "vqtouch.core.frozen": ("vqtouch.plugins.utils.frozen",),
    "vqtouch.core.files": ("vqtouch.plugins.utils.files",),
    "vqtouch.core.cli": ("vqtouch.plugins.cli.app", "vqtouch.plugins.cli.errors"),
    "vqtouch.core.seeding": ("vqtouch.plugins.utils.seeding", "vqtouch.plugins.utils.threads"),
}


def moved_attribute(old_module: str, name: str, homes: tuple[str, ...]) -> Any:
    """``name`` of the moved module ``old_module``, from the first of ``homes`` that has it
    (AttributeError naming the old module otherwise)."""
    if name.startswith("__"):  # the import system's probes (__path__, ...): a moved module is no package
        raise AttributeError(f"module {old_module!r} has no attribute {name!r}")
    for home in homes:
        module = importlib.import_module(home)
        if hasattr(module, name):
            return getattr(module, name)
    raise AttributeError(f"module {old_module!r} has no attribute {name!r}")


def warn_moved(old: str, homes: tuple[str, ...], *, what: str = "module", stacklevel: int = 3) -> None:
    """One-line :class:`VqtouchDeprecationWarning`: ``old`` (a module, or a ``what``) moved to ``homes``."""
    warnings.warn(
        f"{what} {old!r} moved to {' / '.join(homes)} in vqtouch {RENAMED_IN}; import from there "
        f"('{old}' stops working in {REMOVAL_VERSION})",
        VqtouchDeprecationWarning,
        stacklevel=stacklevel,
    )


class _MovedModuleLoader(importlib.abc.Loader):
    """Makes an old module path a stand-in whose attributes come from the new homes."""

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> types.ModuleType:
        homes = MOVED_MODULES[spec.name]
        warn_moved(spec.name, homes, stacklevel=3)
        module = types.ModuleType(spec.name, f"Moved to {', '.join(homes)}.")
        module.__getattr__ = lambda name: moved_attribute(spec.name, name, homes)  # type: ignore[method-assign]
        return module

    def exec_module(self, module: types.ModuleType) -> None:
        """Nothing to run: every attribute is looked up in the new homes."""


class _MovedModuleFinder(importlib.abc.MetaPathFinder):
    def find_spec(self, fullname: str, path: Any = None, target: Any = None) -> importlib.machinery.ModuleSpec | None:
        if fullname not in MOVED_MODULES:
            return None
        return importlib.machinery.ModuleSpec(fullname, _MovedModuleLoader())


def install_moved_modules() -> None:
    """Let the old paths of :data:`MOVED_MODULES` import (once per process)."""
    if not any(isinstance(finder, _MovedModuleFinder) for finder in sys.meta_path):
        sys.meta_path.append(_MovedModuleFinder())

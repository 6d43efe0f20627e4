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
- **Python names**: ``Conditioner.modality`` (now ``sample_key``), ``vqtouch.core.Encoder`` (now
  ``Autoencoder``), ``build_components`` (now :class:`~vqtouch.core.Assembly`): their shims sit
  beside the new names and call :func:`warn_renamed`.  ``load`` without ``host`` is refused (there
  is no hidden plugin host).

The list is the CHANGELOG's "Renamed" section in code; a test checks that every entry is described
there.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

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
    warn_renamed(kind, new, what="component kind", stacklevel=4)
    return new

"""Tokenizer stage: autoencoders (VQGAN, DM-VQGAN, MAE), quantizers, discriminators, losses, training and commands.

The public API other packages use (imported on first use, so importing this package stays light):
:class:`Tokenizer`, loading a trained one, its training objective and settings (adaptation
fine-tunes with them), scoring reconstructions with the experiment's metrics, and the helpers
that show them in reports.  Other packages import these names from here, never the modules
behind them (``make lint`` checks it).
"""

from __future__ import annotations

import importlib
from typing import Any

#: Public name -> (module of this package, name there).  The objective and settings configs come
#: from the light stages_plugin module, so a config that embeds them does not import torch.
_PUBLIC = {
    "TOKENIZER_FILES": ("loading", "TOKENIZER_FILES"),
    "REBASE_FILE": ("loading", "REBASE_FILE"),
    "save_rebase": ("loading", "save_rebase"),
    "tokenizer_paths": ("loading", "tokenizer_paths"),
    "load_tokenizer": ("loading", "load_tokenizer"),
    "reconstruct_all": ("loading", "reconstruct_all"),
    "tokenizer_configs": ("loading", "tokenizer_configs"),
    "tokenizer_digest": ("loading", "tokenizer_digest"),
    "tokenizer_location": ("loading", "tokenizer_location"),
    "TOKENIZER_SHOWN_SCORES": ("stages", "SHOWN_SCORES"),
    "experiment_metrics": ("stages", "experiment_metrics"),
    "printable": ("stages", "printable"),
    "save_pairs": ("stages", "save_pairs"),
    "Tokenizer": ("training", "Tokenizer"),
    "TokenizerLossConfig": ("stages_plugin", "TokenizerLossConfig"),
    "TokenizerTrainConfig": ("stages_plugin", "TokenizerTrainConfig"),
    "disc_start_step": ("stages_plugin", "disc_start_step"),
    "evaluate_reconstruction": ("training", "evaluate_reconstruction"),
    "tokenizer_task": ("training", "tokenizer_task"),
}

__all__ = sorted(_PUBLIC)


def __getattr__(name: str) -> Any:
    if name not in _PUBLIC:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    module, attribute = _PUBLIC[name]
    value = getattr(importlib.import_module(f"{__name__}.{module}"), attribute)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_PUBLIC])

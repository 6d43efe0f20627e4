"""Tokenizer stage: autoencoders (VQGAN, DM-VQGAN, MAE), quantizers, discriminators, losses, training and commands.

The public API other packages use: :class:`Tokenizer`, loading a trained one, its training
objective and settings (adaptation fine-tunes with them), scoring reconstructions with the
experiment's metrics, and the helpers that show them in reports.  Other packages import these
names from here, never the modules behind them (``make lint`` checks it).
"""

from .loading import (
    TOKENIZER_FILES,
    load_tokenizer,
    reconstruct_all,
    tokenizer_configs,
    tokenizer_digest,
    tokenizer_location,
)
from .stages import SHOWN_SCORES as TOKENIZER_SHOWN_SCORES
from .stages import experiment_metrics, printable, save_pairs
from .training import (
    Tokenizer,
    TokenizerLossConfig,
    TokenizerTrainConfig,
    disc_start_step,
    evaluate_reconstruction,
    tokenizer_task,
)

__all__ = [
    "TOKENIZER_FILES",
    "TOKENIZER_SHOWN_SCORES",
    "Tokenizer",
    "TokenizerLossConfig",
    "TokenizerTrainConfig",
    "disc_start_step",
    "evaluate_reconstruction",
    "experiment_metrics",
    "load_tokenizer",
    "printable",
    "reconstruct_all",
    "save_pairs",
    "tokenizer_configs",
    "tokenizer_digest",
    "tokenizer_location",
    "tokenizer_task",
]

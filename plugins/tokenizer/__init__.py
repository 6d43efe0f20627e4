"""Tokenizer stage: autoencoders (VQGAN, DM-VQGAN, MAE), quantizers, discriminators, losses, training and commands.

The public API other packages use: :class:`Tokenizer`, loading a trained one, and its training
objective (adaptation fine-tunes with it).
"""

from .loading import TOKENIZER_FILES, load_tokenizer, reconstruct_all, tokenizer_configs, tokenizer_location
from .training import Tokenizer, tokenizer_task

__all__ = ["TOKENIZER_FILES", "Tokenizer", "load_tokenizer", "reconstruct_all", "tokenizer_configs",
           "tokenizer_location", "tokenizer_task"]

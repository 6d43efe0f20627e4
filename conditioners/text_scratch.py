"""Text conditioner trained from scratch: hashed words -> small transformer encoder -> condition tokens.

It works fully offline and needs no vocabulary file: a text is lower-cased and split into
words at every non-alphanumeric character, and each word is hashed with CRC-32 (stable across
processes, machines and Python versions, unlike the salted built-in ``hash``) into one of
``vocab_buckets`` embedding rows.  Different words may share a bucket (a hashing trick); more
buckets make that rarer.  At most ``max_words`` words are kept (later ones are dropped).

Tokens: one per word position, ``max_words`` in all.  Positions past the text's last word
(padding) carry the mean of the real words' tokens, so a short text's tokens do not depend on
how far it was padded, and attention over them sees the text's summary rather than filler.
An empty text (no words) is encoded as one learned "empty" token (the first position's
embedding), repeated.
"""

from __future__ import annotations

import re
import zlib
from collections.abc import Sequence

import torch
from torch import nn

from vqtouch.core import BuildContext, Conditioner

from .text_scratch_plugin import TextScratchConditionerConfig

#: Embedding row of padding positions (zero and never trained); word buckets are rows 1..vocab_buckets.
PAD_INDEX = 0
#: A word: a maximal run of letters or digits (Unicode-aware; underscores separate words).
_WORD = re.compile(r"[^\W_]+")


def split_words(text: str) -> list[str]:
    """The words of ``text``: lower-cased runs of letters or digits, in order."""
    return _WORD.findall(text.lower())


def word_bucket(word: str, vocab_buckets: int) -> int:
    """Embedding row (1..vocab_buckets) of ``word``: CRC-32 of its UTF-8 bytes, stable across processes."""
    return 1 + zlib.crc32(word.encode("utf-8")) % vocab_buckets


def word_ids(text: str, vocab_buckets: int, max_words: int) -> list[int]:
    """The bucket rows of the first ``max_words`` words of ``text`` (no padding; empty for a text without words)."""
    return [word_bucket(word, vocab_buckets) for word in split_words(text)[:max_words]]


class TextScratchConditioner(Conditioner):
    """Encodes a batch of texts (a list of B strings) into (B, max_words, cond_dim) tokens.

    Hashed word embeddings + learned position embeddings, ``depth`` pre-norm transformer
    encoder layers (padding masked out of attention), a final LayerNorm and a projection to
    ``cond_dim``; padding positions then carry the mean of the real words' tokens (see the
    module docstring).  Everything is trained from scratch with the generator.
    """

    sample_key = "text"

    def __init__(self, cond_dim: int, vocab_buckets: int, max_words: int, width: int, depth: int, heads: int) -> None:
        """Arguments as in :class:`TextScratchConditionerConfig`."""
        super().__init__(cond_dim, max_words)
        self.vocab_buckets = vocab_buckets
        self.max_words = max_words
        self.word_embedding = nn.Embedding(vocab_buckets + 1, width, padding_idx=PAD_INDEX)
        nn.init.normal_(self.word_embedding.weight, std=0.02)
        with torch.no_grad():
            self.word_embedding.weight[PAD_INDEX].zero_()
        self.position_LD = nn.Parameter(torch.randn(max_words, width) * 0.02)
        # Dropout 0: the conditioner already gets condition dropout (null tokens) from the trainer.
        self.layers = nn.ModuleList(
            nn.TransformerEncoderLayer(
                width,
                heads,
                dim_feedforward=4 * width,
                dropout=0.0,
                activation="gelu",
                batch_first=True,
                norm_first=True,
            )
            for _ in range(depth)
        )
        self.norm = nn.LayerNorm(width)
        self.project = nn.Linear(width, cond_dim)

    def word_ids(self, texts: Sequence[str]) -> tuple[torch.Tensor, torch.Tensor]:
        """Bucket rows (B, L) padded with ``PAD_INDEX`` to the longest text (L >= 1) and the (B, L) mask of
        real words."""
        rows = [word_ids(text, self.vocab_buckets, self.max_words) for text in texts]
        length = max([1, *map(len, rows)])
        device = self.word_embedding.weight.device
        ids_BL = torch.full((len(rows), length), PAD_INDEX, dtype=torch.long)
        for index, row in enumerate(rows):
            ids_BL[index, : len(row)] = torch.tensor(row, dtype=torch.long)
        ids_BL = ids_BL.to(device)
        return ids_BL, ids_BL != PAD_INDEX

    def encode(self, condition: Sequence[str]) -> torch.Tensor:
        """Texts (a list or tuple of B strings) to tokens (B, max_words, cond_dim)."""
        texts = condition
        if not isinstance(texts, (list, tuple)) or not all(isinstance(text, str) for text in texts):
            got = (
                f"a {type(texts).__name__} with non-strings"
                if isinstance(texts, (list, tuple))
                else (type(texts).__name__)
            )
            raise ValueError(f"text_scratch conditioner expects a list of B strings, got {got}")
        ids_BL, real_BL = self.word_ids(texts)
        # An empty text has no word to attend to; its first (padding) position stands in for it, so every row
        # attends to something (an all-masked row would give NaN) and the empty text gets a learned encoding.
        attend_BL = real_BL.clone()
        attend_BL[:, 0] = True
        length = ids_BL.shape[1]
        hidden_BLD = self.word_embedding(ids_BL) + self.position_LD[:length]
        for layer in self.layers:
            hidden_BLD = layer(hidden_BLD, src_key_padding_mask=~attend_BL)
        tokens_BLC = self.project(self.norm(hidden_BLD))
        # Padding positions (and the positions past the batch's longest text) carry the mean of the real tokens.
        # torch.where, not a multiply by the mask: whatever a padding row holds must not leak into the mean.
        attend_BL1 = attend_BL.unsqueeze(-1)
        real_sum_B1C = torch.where(attend_BL1, tokens_BLC, 0).sum(1, keepdim=True)
        mean_B1C = real_sum_B1C / attend_BL1.sum(1, keepdim=True).to(tokens_BLC.dtype)
        tokens_BLC = torch.where(attend_BL1, tokens_BLC, mean_B1C)
        return torch.cat([tokens_BLC, mean_B1C.expand(-1, self.max_words - length, -1)], dim=1)

    def extra_repr(self) -> str:
        return f"vocab_buckets={self.vocab_buckets}, max_words={self.max_words}"


def build_text_scratch_conditioner(
    config: TextScratchConditionerConfig, context: BuildContext
) -> TextScratchConditioner:
    """Factory for the ``text_scratch`` conditioner."""
    return TextScratchConditioner(
        context.cond_dim, config.vocab_buckets, config.max_words, config.width, config.depth, config.heads
    )

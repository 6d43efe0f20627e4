"""Text conditioner: the frozen text tower of an open_clip model loaded from a local file (text-to-touch).

The counterpart of the ``clip`` conditioner (:mod:`.clip`) for texts, built the same way and on
the same helpers: open_clip (and with it torchvision's model code) is imported only when this
conditioner is built; the weights come from a local open_clip checkpoint (the same file the
``clip`` conditioner reads, found the same way: the ``checkpoint`` option, ``VQTOUCH_CLIP_CKPT``
or ``VQTOUCH_WEIGHTS_DIR``) and are never downloaded; the network is held in a
:class:`vqtouch.plugins.utils.frozen.FrozenModule`, so it is frozen, always in eval mode and not copied
into vqtouch checkpoints (they record the architecture and the file path; only the trainable
projection and the null tokens are saved).  The image tower is dropped once the file is loaded.

Tokens: a text is tokenized with open_clip's own tokenizer for the architecture (the BPE
``SimpleTokenizer``, whose vocabulary ships inside the open_clip wheel; architectures whose
tokenizer would come from the Hugging Face Hub are refused) into ``context_length`` positions:
start-of-text, the text's BPE tokens, end-of-text, then padding (id 0, as open_clip pads).  A
longer text is truncated and its last kept position becomes end-of-text, as open_clip truncates.
The ids are padded to the model's own context length, the frozen text transformer runs over them
and the final hidden state of each of the first ``context_length`` positions (after the tower's
final LayerNorm, before CLIP's pooling and text projection) is mapped to ``cond_dim`` by one
trainable linear layer: ``context_length`` condition tokens per text.  CLIP's text transformer is
causal, so position ``i`` sees only positions ``0..i``: the padding beyond ``context_length`` does
not change the kept states, and the padding positions inside the window carry states that have
seen the whole text (they are kept as the tower computes them).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from vqtouch.core import BuildContext, Conditioner, ConfigError
from vqtouch.plugins.utils.weights import WeightsSpec, resolve_weights
from vqtouch.plugins.utils.frozen import FrozenModule

from vqtouch.plugins.evaluation.open_clip_towers import (
    builtin_tokenizer,
    check_open_clip_architecture,
    create_open_clip_model,
    import_open_clip,
)

from .clip import CLIP_WEIGHTS
from .clip_text_plugin import TextConditionerConfig

#: The same open_clip checkpoint file the ``clip`` conditioner reads (it holds both towers), found the same way.
TEXT_WEIGHTS = WeightsSpec(
    description="conditioner 'text' (frozen open_clip text encoder)",
    filenames=CLIP_WEIGHTS.filenames,
    env_var=CLIP_WEIGHTS.env_var,
    source_url=CLIP_WEIGHTS.source_url,
    config_hint="the text conditioner's checkpoint option (e.g. --set generator.conditioners.0.checkpoint=PATH)",
)


def text_hidden_states(model: nn.Module, ids_BL: torch.Tensor) -> torch.Tensor:
    """Final hidden states (B, L, width) of open_clip ``model``'s text transformer for token ids (B, L),
    after the tower's final LayerNorm and before pooling and the text projection.

    ``L`` must be the model's context length (its position embeddings have that many rows).
    Uses open_clip's ``forward_intermediates`` (last block, final norm applied), which both
    ``CLIP`` and ``CustomTextCLIP`` models implement.
    """
    output = model.forward_intermediates(
        text=ids_BL, text_indices=1, normalize_intermediates=True, intermediates_only=True
    )
    return output["text_intermediates"][-1]


class TextConditioner(Conditioner):
    """Texts (a list of B strings) -> frozen open_clip text tower -> per-token final hidden states ->
    trainable linear projection -> (B, context_length, cond_dim) tokens (see the module docstring)."""

    sample_key = "text"

    def __init__(
        self,
        clip_model: nn.Module,
        tokenizer: Any,
        width: int,
        model_context_length: int,
        cond_dim: int,
        context_length: int,
    ) -> None:
        """``clip_model``: the loaded open_clip model (frozen here); ``tokenizer``: its built-in tokenizer
        (see :func:`builtin_tokenizer`); ``width``: its text transformer's width; ``model_context_length``:
        the length its position embeddings need; ``context_length``: positions kept (condition tokens)."""
        super().__init__(cond_dim, context_length)
        # Frozen, always in eval mode, out of state_dict and checkpoints, moved by .to() (see FrozenModule).
        self.encoder = FrozenModule(clip_model)
        self.tokenizer = tokenizer
        self.context_length = context_length
        self.model_context_length = model_context_length
        self.project = nn.Linear(width, cond_dim)

    def token_ids(self, texts: Sequence[str]) -> torch.Tensor:
        """open_clip token ids (B, context_length) of ``texts``: start-of-text, BPE tokens, end-of-text,
        zero padding; a longer text is truncated with end-of-text as its last kept id."""
        return self.tokenizer(list(texts), context_length=self.context_length)

    def hidden_states(self, texts: Sequence[str]) -> torch.Tensor:
        """The frozen tower's final hidden states (B, context_length, width) of ``texts`` (no gradient)."""
        ids_BN = self.token_ids(texts)
        ids_BL = F.pad(ids_BN, (0, self.model_context_length - self.context_length))  # causal: changes no kept state
        with torch.no_grad():
            hidden_BLW = text_hidden_states(self.encoder.network, ids_BL.to(self.project.weight.device))
        return hidden_BLW[:, : self.context_length].float()

    def encode(self, condition: Sequence[str]) -> torch.Tensor:
        """Texts (a list or tuple of B strings) to tokens (B, context_length, cond_dim)."""
        texts = condition
        if not isinstance(texts, (list, tuple)) or not all(isinstance(text, str) for text in texts):
            got = (
                f"a {type(texts).__name__} with non-strings"
                if isinstance(texts, (list, tuple))
                else (type(texts).__name__)
            )
            raise ValueError(f"text conditioner expects a list of B strings, got {got}")
        return self.project(self.hidden_states(texts))

    def extra_repr(self) -> str:
        """The kept context length, shown in ``print(model)``."""
        return f"context_length={self.context_length}"


def build_text_conditioner(config: TextConditionerConfig, context: BuildContext) -> TextConditioner:
    """Factory: import open_clip (the ``clip`` extra), resolve the local weights file (never downloads),
    check the architecture's tokenizer works offline, load the model and keep its frozen text tower."""
    open_clip = import_open_clip("text")
    path = resolve_weights(TEXT_WEIGHTS, config.checkpoint)
    check_open_clip_architecture(open_clip, config.architecture, "text")
    tokenizer = builtin_tokenizer(open_clip, config.architecture, config.context_length, config.model_overrides)
    model = create_open_clip_model(open_clip, config.architecture, path, config.model_overrides, "text")
    model_context_length = getattr(model, "context_length", None)
    if not isinstance(model_context_length, int) or not hasattr(model, "forward_intermediates"):
        raise ConfigError(
            f"conditioner 'text': open_clip architecture {config.architecture!r} has no text "
            "transformer this conditioner can read; choose a CLIP model (e.g. ViT-B-32)"
        )
    if config.context_length > model_context_length:
        raise ConfigError(
            f"conditioner 'text': context_length={config.context_length} exceeds "
            f"{config.architecture}'s context length {model_context_length}"
        )
    model.visual = nn.Identity()  # text-to-touch never uses the image tower: do not keep its weights in memory
    model.eval().requires_grad_(False)
    with torch.no_grad():
        try:
            probe = F.pad(
                tokenizer([""], context_length=config.context_length), (0, model_context_length - config.context_length)
            )
            width = text_hidden_states(model, probe).shape[-1]
        except (IndexError, RuntimeError) as exc:
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise ConfigError(
                f"conditioner 'text': {config.architecture}'s text tower cannot read open_clip's tokens ({first})"
            ) from None
    return TextConditioner(model, tokenizer, width, model_context_length, context.cond_dim, config.context_length)

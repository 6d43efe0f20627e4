"""Label conditioner: one learned embedding (a few tokens) per class label."""

from __future__ import annotations

import torch
from torch import nn

from vqtouch.core import BuildContext, Conditioner

from .label_plugin import LabelConditionerConfig


class LabelConditioner(Conditioner):
    """Embeds integer class labels (B,) into (B, num_tokens, cond_dim) tokens."""

    sample_key = "label"

    def __init__(self, num_classes: int, cond_dim: int, num_tokens: int = 1) -> None:
        super().__init__(cond_dim, num_tokens)
        self.num_classes = num_classes
        self.embedding = nn.Embedding(num_classes, num_tokens * cond_dim)
        nn.init.normal_(self.embedding.weight, std=0.02)

    def encode(self, condition: torch.Tensor) -> torch.Tensor:
        """Labels (B,) of integer dtype in [0, num_classes) to tokens (B, num_tokens, cond_dim)."""
        labels_B = torch.as_tensor(condition, device=self.embedding.weight.device)
        if labels_B.dtype.is_floating_point or labels_B.dtype == torch.bool or labels_B.ndim != 1:
            raise ValueError(
                f"label conditioner expects a 1-D integer tensor of labels, got "
                f"{labels_B.dtype} with shape {tuple(labels_B.shape)}"
            )
        if labels_B.numel() and (labels_B.min() < 0 or labels_B.max() >= self.num_classes):
            raise ValueError(
                f"labels must be in [0, {self.num_classes}); got min {int(labels_B.min())}, "
                f"max {int(labels_B.max())}. Use the drop mask for 'no label'"
            )
        return self.embedding(labels_B.long()).view(-1, self.num_tokens, self.cond_dim)


def build_label_conditioner(config: LabelConditionerConfig, context: BuildContext) -> LabelConditioner:
    """Factory: the class count comes from the config, else from the dataset via the context."""
    num_classes = config.num_classes or context.num_classes
    if config.num_classes and context.num_classes > config.num_classes:
        from vqtouch.core import ConfigError

        raise ConfigError(
            f"conditioner 'label' has num_classes={config.num_classes} but the dataset has "
            f"{context.num_classes} classes; set num_classes=0 to take the dataset's count"
        )
    if num_classes < 1:
        from vqtouch.core import ConfigError

        raise ConfigError(
            "conditioner 'label' needs the number of classes: set conditioner.num_classes=N or use a labelled dataset"
        )
    return LabelConditioner(num_classes, context.cond_dim, config.num_tokens)

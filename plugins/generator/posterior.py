"""Best of K by the generator's own class posterior: of K candidates for a label, keep the one the
generator itself finds most likely to be of that class.

The generator's likelihoods make an implicit classifier, p(class | x) proportional to p(x | class) for
equal priors, read here by :meth:`~.vq_diffusion.VQDiffusion.masked_log_likelihood` under every class;
of K candidates the one with the highest posterior at its own class is kept.  No other model is
involved.  Cost per candidate: its sampling plus four forward passes per class (with 12 classes, about
as much again as a guided 25-step draw); measured in docs/generation.md.  It names the class of real
held-out codes about half the time, the code judge (:mod:`.judge`) about 3 times in 4.
"""

from __future__ import annotations

from typing import Any

import torch

from vqtouch.core import ConfigError
from vqtouch.core.components import BestOfBatch, BestOfRanker


@torch.no_grad()
def class_log_posteriors(generator: Any, conditioner: Any, codes_BHW: torch.Tensor) -> torch.Tensor:
    """(num_classes, B): log p(class | codes) of every class under the generator's own likelihoods
    (:meth:`masked_log_likelihood` under each class's condition, normalised over the classes)."""
    if not hasattr(generator, "masked_log_likelihood"):
        raise ConfigError(
            f"best of K needs a generator that scores its codes (masked_log_likelihood); "
            f"{type(generator).__name__} does not"
        )
    rows = len(codes_BHW)
    log_likelihoods_CB = torch.stack(
        [
            generator.masked_log_likelihood(
                codes_BHW, conditioner(torch.full((rows,), label, dtype=torch.long, device=codes_BHW.device))
            )
            for label in range(conditioner.num_classes)
        ]
    )
    return log_likelihoods_CB.log_softmax(0)


class PosteriorRanker(BestOfRanker):
    """Scores a candidate by the generator's log posterior of its row's class (:func:`class_log_posteriors`)."""

    needs_classes = True

    def score(self, codes_BHW: torch.Tensor, batch: BestOfBatch) -> torch.Tensor:
        labels_B = batch.conditions
        rows_B = torch.arange(len(labels_B), device=labels_B.device)
        return class_log_posteriors(batch.generator, batch.conditioner, codes_BHW)[labels_B, rows_B]


def build_posterior_ranker(config: Any, context: Any) -> PosteriorRanker:
    """The ``posterior`` ranker (it has no options)."""
    return PosteriorRanker()

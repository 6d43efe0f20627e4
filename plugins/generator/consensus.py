"""Best of K by consensus: of K candidates for a condition, keep the one whose contact lies where the
others agree it lies.

The code judge (:mod:`.judge`) and the generator's posterior rank a candidate by its class, so they
need a label.  A visual or tactile condition names no class; what it fixes is where and how the object
touches the gel.  Each candidate is one draw of that place; the mean of K draws is a better estimate
of it than any one draw (it averages the sampling spread out), but the mean of K images is a blur, not
a sample.  So this keeps the medoid: the candidate whose contact centre has the least summed distance
to the other candidates' contact centres (minimum Bayes risk under that distance; no other model, no
class).  The contact centre is :func:`~vqtouch.plugins.evaluation.contact.contact_centroids` of the
decoded candidate against the run's no-contact image.

Measured on the bundle's 64 held-out visual conditions (docs/generation.md): best of 8
brings the contact centre from 5.28 to 4.81 px from the truth's (three sampling seeds).  The mean of
the candidates' centres is itself about 4.5 px off: the medoid removes the sampling spread, not the
generator's own error in the place, so more candidates gain little more.  For a label the same rule
keeps the most typical-looking candidate, which is not the one a classifier names right more often;
use the judge there.
"""

from __future__ import annotations

from typing import Any

import torch

from vqtouch.core import ConfigError
from vqtouch.core.components import BestOfBatch, BestOfRanker


class ContactConsensus:
    """Chooses, per row, the candidate whose contact centre is the medoid of the K candidates' centres.

    ``tokenizer`` decodes the candidates' codes; ``background_3HW`` is the no-contact image the contact
    is measured against (the run's, :func:`~vqtouch.plugins.evaluation.contact.dataset_background`)."""

    def __init__(self, tokenizer: Any, background_3HW: torch.Tensor) -> None:
        if background_3HW.ndim != 3 or background_3HW.shape[0] != 3:
            raise ValueError(
                f"ContactConsensus: the no-contact image must be (3, H, W); got {tuple(background_3HW.shape)}"
            )
        self.tokenizer = tokenizer
        self.background_3HW = background_3HW

    @torch.no_grad()
    def centres(self, codes_BHW: torch.Tensor) -> torch.Tensor:
        """(B, 2) the (row, column) contact centre of each decoded code grid, in pixels."""
        from vqtouch.plugins.evaluation.contact import contact_centroids

        # One grid at a time, as the pipeline decodes its samples: the decoder's rounding depends on the
        # batch size, and a choice must not depend on the batch a row falls in.
        images_B3HW = torch.cat([self.tokenizer.decode_codes(grid.unsqueeze(0)).float().cpu() for grid in codes_BHW])
        background = self.background_3HW.float().cpu()
        if background.shape[-2:] != images_B3HW.shape[-2:]:
            raise ValueError(
                f"ContactConsensus: the no-contact image is {tuple(background.shape[-2:])} pixels, the decoded "
                f"candidates {tuple(images_B3HW.shape[-2:])}"
            )
        # One image at a time too: the contact mask's noise floor is a median over the images it is given.
        return torch.cat([contact_centroids(image.clamp(0, 1)[None], background[None]) for image in images_B3HW])

    def choose(self, candidates_KBHW: torch.Tensor) -> torch.Tensor:
        """(B,) long: per row, the index in [0, K) of the candidate whose contact centre has the least
        summed distance to the other candidates' centres; ties keep the earliest."""
        if candidates_KBHW.ndim != 4 or not len(candidates_KBHW):
            raise ValueError(
                f"ContactConsensus: expected candidates (K >= 1, B, H, W); got {tuple(candidates_KBHW.shape)}"
            )
        centres_BK2 = torch.stack([self.centres(codes_BHW) for codes_BHW in candidates_KBHW], 1)
        distances_BKK = torch.cdist(centres_BK2.double(), centres_BK2.double())
        return medoid_indices(distances_BKK)


def medoid_indices(distances_BKK: torch.Tensor) -> torch.Tensor:
    """(B,) long: per row, the index of the item with the least summed distance to the others
    (``distances_BKK[b, i, j]``, symmetric); ties keep the earliest."""
    total_BK = distances_BKK.sum(-1)
    best_B = total_BK.min(-1, keepdim=True).values
    # argmin's tie order is not specified across devices; the first index within a relative 1e-12 is.
    tied_BK = total_BK <= best_B * (1 + 1e-12)
    positions = torch.arange(total_BK.shape[-1], device=total_BK.device)
    return torch.where(tied_BK, positions, total_BK.shape[-1]).min(-1).values


class ConsensusRanker(BestOfRanker):
    """Chooses by :class:`ContactConsensus` over the run's tokenizer and the no-contact image of its
    training split (the one ``vqtouch evaluate generation`` scores contacts against), read when a
    pipeline first ranks with it; reads no classes."""

    def __init__(self) -> None:
        self.consensus: ContactConsensus | None = None

    def prepare(self, pipeline: Any) -> None:
        _, background_3HW, source = pipeline.training_split("best of K by consensus")
        if background_3HW is None:
            raise ConfigError(f"best of K by consensus needs a no-contact image; this run's data give {source}")
        self.consensus = ContactConsensus(pipeline.tokenizer, background_3HW)

    def choose(self, candidates_KBHW: torch.Tensor, batch: BestOfBatch) -> torch.Tensor:
        if self.consensus is None:
            raise RuntimeError("the consensus ranker chooses after prepare(pipeline) has read the no-contact image")
        return self.consensus.choose(candidates_KBHW)


def build_consensus_ranker(config: Any, context: Any) -> ConsensusRanker:
    """The ``consensus`` ranker (it has no options)."""
    return ConsensusRanker()

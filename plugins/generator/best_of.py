"""Best of K: draw several candidates per condition and keep the one a ranker prefers.

The rankers are plugins (``vqtouch_register_best_of_rankers``, a :class:`vqtouch.core.BestOfRanker`;
the built-ins in rankers_plugin.py): a classifier of code grids fitted on the run's training codes
(``judge``, :mod:`.judge`, the default of the commands: it names held-out real codes about 3 times in
4), the generator's own class posterior (``posterior``, :mod:`.posterior`; no other model), or, for any
condition and without a class, the candidates' consensus on where the contact lies (``consensus``,
:mod:`.consensus`).  ``--best-of-rank NAME`` chooses one; the pipeline builds and prepares it
(:meth:`.pipeline.GenerationPipeline.best_of_ranking`).

A label leaves the generator to invent the pose and every fine texture that tells classes apart, and
at the compute of a CPU hour a single draw is named right by a classifier about 40-50% of the time
(docs/generation.md).

Candidate 0 of a row is drawn with the row's own generator, so ``best_of=1`` is plain sampling, bit
for bit; candidate j > 0 with a generator seeded by a hash of the row's seed and j
(:func:`candidate_seed`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

from vqtouch.core import ConfigError

from .rankers_plugin import DEFAULT_RANKER

if TYPE_CHECKING:
    import torch

    from vqtouch.core import BestOfRanker, PluginHost

#: The most candidates a condition may draw.
MAX_BEST_OF = 64
#: The registry kind of best of K's rankers.
RANKER_KIND = "best_of_ranker"
_MASK64 = 2**64 - 1


def _no_grad(function: Callable[..., Any]) -> Callable[..., Any]:
    """``torch.no_grad()`` around ``function``, torch imported at the first call: the commands' handlers
    import this module before they know whether anything is sampled."""

    @functools.wraps(function)
    def without_gradients(*args: Any, **kwargs: Any) -> Any:
        import torch

        with torch.no_grad():
            return function(*args, **kwargs)

    return without_gradients


def _mix64(value: int) -> int:
    """SplitMix64's finaliser: every output bit depends on every input bit."""
    value = (value ^ (value >> 30)) * 0xBF58476D1CE4E5B9 & _MASK64
    value = (value ^ (value >> 27)) * 0x94D049BB133111EB & _MASK64
    return value ^ (value >> 31)


def candidate_seed(row_seed: int, candidate: int) -> int:
    """The seed of candidate ``candidate`` of a row drawn with seed ``row_seed``: the row's own seed for
    candidate 0, else a hash of both.  Why a hash rather than an offset: a CPU ``torch.Generator``
    reads only the low 32 bits of its seed, so an offset in the high bits would repeat candidate 0;
    hashed, two candidates share a stream only by a 2**-32 chance."""
    if not 0 <= candidate < MAX_BEST_OF:
        raise ValueError(f"candidate {candidate} must lie in [0, {MAX_BEST_OF})")
    if candidate == 0:
        return row_seed
    return _mix64((row_seed * 0x9E3779B97F4A7C15 + candidate) & _MASK64) >> 1  # below 2**63


def ranks_by_class(conditioner: Any) -> bool:
    """Whether a class ranker can rank ``conditioner``'s candidates: it conditions on one of a finite set
    of classes (it has an integer ``num_classes``, as the label conditioner does)."""
    return isinstance(getattr(conditioner, "num_classes", None), int)


def check_best_of_rank(rank: Any, host: PluginHost) -> str:
    """``rank`` as given when ``host`` has a best-of ranker of that name, or a one-line ConfigError
    naming the registered ones."""
    registry = host.registry(RANKER_KIND)
    if not isinstance(rank, str) or rank not in registry:
        raise ConfigError(f"--best-of-rank {rank!r}: choose one of {', '.join(registry.names())}")
    return rank


def rank_name(rank: Any) -> str:
    """The registered name of a ranker as :func:`sample_best_of` takes it (None: the generator's
    posterior), for the records."""
    if rank is None:
        return "posterior"
    spec = getattr(rank, "vqtouch_spec", None)
    return spec.config.name if spec is not None else type(rank).__name__


def refuse_idle_rank(args: Any) -> None:
    """A one-line ConfigError for a ``--best-of-rank`` that names no registered ranker (of the command's
    host, ``args.host``), or that is given without ``--best-of K`` (K > 1): it ranks candidates, and one
    draw has none."""
    from vqtouch.plugins.cli.app import option_given

    check_best_of_rank(args.best_of_rank, args.host)
    best_of = args.best_of if isinstance(args.best_of, (list, tuple)) else [args.best_of]
    if option_given(args, "--best-of-rank") and max(best_of or [1]) <= 1:
        raise ConfigError(
            f"--best-of-rank {args.best_of_rank} ranks --best-of's candidates, and one draw has none: add "
            "--best-of K (K > 1, e.g. 8), or drop --best-of-rank"
        )


def check_best_of(best_of: Any, conditioner: Any, name: str, rank: BestOfRanker | None = None) -> int:
    """``best_of`` as given, or a one-line ConfigError: an integer in [1, MAX_BEST_OF], and above 1 with
    a ranker that ranks by class (``rank.needs_classes``; None: the default ranker, the judge, which
    does) only for a conditioner over a finite set of classes (one with ``num_classes``, the label's);
    a ranker that reads no classes, such as ``consensus``, ranks any conditioner's candidates.  ``name``
    names the conditioner in the message."""
    if isinstance(best_of, bool) or not isinstance(best_of, int) or not 1 <= best_of <= MAX_BEST_OF:
        raise ConfigError(f"--best-of {best_of}: give an integer in [1, {MAX_BEST_OF}] (1: plain sampling)")
    needs_classes = True if rank is None else rank.needs_classes
    if best_of > 1 and needs_classes and not ranks_by_class(conditioner):
        shown = DEFAULT_RANKER if rank is None else rank_name(rank)
        raise ConfigError(
            f"--best-of {best_of} --best-of-rank {shown}: conditioner {name} has no finite set of classes to "
            "rank candidates by; use a ranker that reads no classes, such as --best-of-rank consensus (the "
            "candidates' agreement on the contact), or --best-of 1"
        )
    return best_of


def _ranked_conditions(rank: Any, labels_B: Any, rows: int, device: torch.device) -> Any:
    """The rows' conditions as ``rank`` reads them: for a ranker by class, the labels as a long tensor
    (B,) on ``device`` (a ValueError when there are none or not one per row); else as given."""
    import torch

    if not rank.needs_classes:
        return labels_B
    if labels_B is None:
        raise ValueError("best of K > 1 needs the rows' labels")
    labels_B = torch.as_tensor(labels_B, device=device).long().view(-1)
    if len(labels_B) != rows:
        raise ValueError(f"{len(labels_B)} labels for {rows} row seeds")
    return labels_B


@_no_grad
def sample_best_of(
    generator: Any,
    conditioner: Any,
    labels_B: Any,
    row_seeds: Sequence[int],
    best_of: int,
    draw: Callable[[list[torch.Generator]], torch.Tensor],
    device: torch.device,
    rank: BestOfRanker | None = None,
) -> torch.Tensor:
    """Codes (B, H, W): per row, the candidate of ``best_of`` that the ranker ``rank`` keeps
    (:meth:`~vqtouch.core.BestOfRanker.choose`, already prepared, e.g. by
    :meth:`.pipeline.GenerationPipeline.best_of_ranking`), or, when None, the one with the generator's
    highest posterior of the row's label (:class:`.posterior.PosteriorRanker`).  ``labels_B``: the rows'
    conditions (their labels, for a ranker by class).  ``draw(generators)`` samples one candidate per row
    with the given generators (the caller's sampler, steps, guidance and condition); ``row_seeds[b]`` is
    row b's own seed (candidate 0).  With ``best_of=1`` this is ``draw`` with the rows' own generators,
    and ``labels_B`` may be None."""
    import torch

    from vqtouch.core.components import BestOfBatch

    if best_of == 1:
        return draw([torch.Generator(device=device).manual_seed(seed) for seed in row_seeds])
    if rank is None:
        from .posterior import PosteriorRanker

        rank = PosteriorRanker()
    batch = BestOfBatch(generator, conditioner, _ranked_conditions(rank, labels_B, len(row_seeds), device))
    candidates_KBHW = torch.stack(
        [
            draw([torch.Generator(device=device).manual_seed(candidate_seed(seed, k)) for seed in row_seeds])
            for k in range(best_of)
        ]
    )
    chosen_B = rank.choose(candidates_KBHW, batch).to(candidates_KBHW.device)
    return candidates_KBHW[chosen_B, torch.arange(candidates_KBHW.shape[1], device=chosen_B.device)]

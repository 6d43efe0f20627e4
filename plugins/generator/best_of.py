"""Best of K: draw several candidates per class label and keep the one a judge finds most typical of
the asked class.

Three rankings (``rank``): a classifier of code grids fitted on the run's training codes
(:mod:`.judge`, the default of the commands: it names held-out real codes about 3 times in 4), the
generator's own class posterior (``posterior``, below; no other model), or, for any condition and
without a class, the candidates' consensus on where the contact lies (``consensus``,
:mod:`.consensus`).

A label leaves the generator to invent the pose and every fine texture that tells classes apart, and
at the compute of a CPU hour a single draw is named right by a classifier about 40-50% of the time
(docs/generation.md).  The generator's own likelihoods make an implicit classifier,
p(class | x) proportional to p(x | class) for equal priors, read here by
:meth:`~.vq_diffusion.VQDiffusion.masked_log_likelihood` under every class; of K candidates the one
with the highest posterior at its own class is kept.  No other model is involved.  Cost per
candidate: its sampling plus four forward passes per class (with 12 classes, about as much again as
a guided 25-step draw); measured in docs/generation.md.

Candidate 0 of a row is drawn with the row's own generator, so ``best_of=1`` is plain sampling, bit
for bit; candidate j > 0 with a generator seeded by a hash of the row's seed and j
(:func:`candidate_seed`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, Literal

from vqtouch.core import ConfigError

if TYPE_CHECKING:
    import torch

#: The most candidates a condition may draw.
MAX_BEST_OF = 64
#: What can rank best of K's candidates: the code judge (:mod:`.judge`), the generator's posterior, or
#: the candidates' consensus on the contact (:mod:`.consensus`; the only one for a condition without classes).
BEST_OF_RANKS = ("judge", "posterior", "consensus")
BestOfRank = Literal["judge", "posterior", "consensus"]
#: What each ranking is, in words (the commands' help and the reports).
RANK_DESCRIPTIONS = {
    "judge": "a classifier of code grids fitted on the run's training codes",
    "posterior": "the generator's own class posterior",
    "consensus": "the candidate whose contact centre the others agree on most (any condition, no class)",
}
#: ``--best-of-rank``'s help, shared by every command that takes it.
_JUDGE_COST = " (fitted once, about a minute)"
BEST_OF_RANK_HELP = "what ranks --best-of's candidates: " + "; ".join(
    f"{name} (default), {text}{_JUDGE_COST}" if name == "judge" else f"{name}, {text}"
    for name, text in RANK_DESCRIPTIONS.items()
)
#: Rankings that need the rows' classes.
CLASS_RANKS = ("judge", "posterior")
#: A ranking: (codes (B, H, W), labels (B,)) -> (B,) scores, higher is better.  A ranking object with a
#: ``choose(candidates (K, B, H, W)) -> (B,)`` method (:class:`.consensus.ContactConsensus`) instead
#: sees all K candidates of a row at once.
Rank = Callable[["torch.Tensor", "torch.Tensor"], "torch.Tensor"]
_MASK64 = 2**64 - 1


def _no_grad(function: Callable[..., Any]) -> Callable[..., Any]:
    """``torch.no_grad()`` around ``function``, torch imported at the first call: the commands read this
    module's choices and help text for their parsers, which must not import torch."""

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
    """Whether best of K can rank ``conditioner``'s candidates: it conditions on one of a finite set of
    classes (it has an integer ``num_classes``, as the label conditioner does)."""
    return isinstance(getattr(conditioner, "num_classes", None), int)


def check_best_of_rank(rank: Any) -> BestOfRank:
    """``rank`` as given, or a one-line ConfigError naming the choices."""
    if rank not in BEST_OF_RANKS:
        raise ConfigError(f"--best-of-rank {rank!r}: choose one of {', '.join(BEST_OF_RANKS)}")
    return rank


def rank_name(rank: Any) -> BestOfRank:
    """The :data:`BEST_OF_RANKS` name of a ranking as :func:`sample_best_of` takes it (None: the
    generator's posterior), for the records."""
    if rank is None:
        return "posterior"
    return "consensus" if hasattr(rank, "choose") else "judge"


def refuse_idle_rank(args: Any) -> None:
    """A one-line ConfigError for ``--best-of-rank`` given without ``--best-of K`` (K > 1): it ranks
    candidates, and one draw has none."""
    from vqtouch.plugins.cli.app import option_given

    best_of = args.best_of if isinstance(args.best_of, (list, tuple)) else [args.best_of]
    if option_given(args, "--best-of-rank") and max(best_of or [1]) <= 1:
        raise ConfigError(
            f"--best-of-rank {args.best_of_rank} ranks --best-of's candidates, and one draw has none: add "
            "--best-of K (K > 1, e.g. 8), or drop --best-of-rank"
        )


def check_best_of(best_of: Any, conditioner: Any, name: str, rank: Any = "judge") -> int:
    """``best_of`` as given, or a one-line ConfigError: an integer in [1, MAX_BEST_OF], and above 1
    with a class ranking (``rank`` ``judge`` or ``posterior``) only for a conditioner over a finite set
    of classes (one with ``num_classes``, the label's); ``consensus`` ranks any conditioner's
    candidates.  ``name`` names the conditioner in the message."""
    if isinstance(best_of, bool) or not isinstance(best_of, int) or not 1 <= best_of <= MAX_BEST_OF:
        raise ConfigError(f"--best-of {best_of}: give an integer in [1, {MAX_BEST_OF}] (1: plain sampling)")
    if best_of > 1 and rank in CLASS_RANKS and not ranks_by_class(conditioner):
        raise ConfigError(
            f"--best-of {best_of} --best-of-rank {rank}: conditioner {name} has no finite set of classes to "
            "rank candidates by; use --best-of-rank consensus (the candidates' agreement on the contact) "
            "or --best-of 1"
        )
    return best_of


@_no_grad
def class_log_posteriors(generator: Any, conditioner: Any, codes_BHW: torch.Tensor) -> torch.Tensor:
    """(num_classes, B): log p(class | codes) of every class under the generator's own likelihoods
    (:meth:`masked_log_likelihood` under each class's condition, normalised over the classes)."""
    if not hasattr(generator, "masked_log_likelihood"):
        raise ConfigError(
            f"best of K needs a generator that scores its codes (masked_log_likelihood); "
            f"{type(generator).__name__} does not"
        )
    import torch

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


@_no_grad
def sample_best_of(
    generator: Any,
    conditioner: Any,
    labels_B: torch.Tensor | None,
    row_seeds: Sequence[int],
    best_of: int,
    draw: Callable[[list[torch.Generator]], torch.Tensor],
    device: torch.device,
    rank: Rank | None = None,
) -> torch.Tensor:
    """Codes (B, H, W): per row, the best of ``best_of`` candidates by ``rank(codes, labels)`` (e.g. a
    :meth:`.judge.CodeJudge.rank`), by ``rank.choose(candidates)`` when the ranking has that method
    (:class:`.consensus.ContactConsensus`, which reads no labels), or, when None, by the generator's
    posterior of the row's label (:func:`class_log_posteriors`).  ``draw(generators)`` samples one candidate per row
    with the given generators (the caller's sampler, steps, guidance and condition);
    ``row_seeds[b]`` is row b's own seed (candidate 0).  Ties keep the earliest candidate.  With
    ``best_of=1`` this is ``draw`` with the rows' own generators, and ``labels_B`` may be None."""
    import torch

    if best_of == 1:
        return draw([torch.Generator(device=device).manual_seed(seed) for seed in row_seeds])
    choose = getattr(rank, "choose", None)
    if choose is not None:
        candidates_KBHW = torch.stack(
            [
                draw([torch.Generator(device=device).manual_seed(candidate_seed(seed, k)) for seed in row_seeds])
                for k in range(best_of)
            ]
        )
        chosen_B = choose(candidates_KBHW).to(candidates_KBHW.device)
        return candidates_KBHW[chosen_B, torch.arange(candidates_KBHW.shape[1], device=chosen_B.device)]
    if labels_B is None:
        raise ValueError("best of K > 1 needs the rows' labels")
    labels_B = torch.as_tensor(labels_B, device=device).long().view(-1)
    if len(labels_B) != len(row_seeds):
        raise ValueError(f"{len(labels_B)} labels for {len(row_seeds)} row seeds")
    rows_B = torch.arange(len(labels_B), device=device)
    best_codes = best_score_B = None
    for candidate in range(best_of):
        generators = [torch.Generator(device=device).manual_seed(candidate_seed(seed, candidate)) for seed in row_seeds]
        codes_BHW = draw(generators)
        if rank is None:
            score_B = class_log_posteriors(generator, conditioner, codes_BHW)[labels_B, rows_B]
        else:
            score_B = rank(codes_BHW, labels_B).to(device)
        if best_codes is None:
            best_codes, best_score_B = codes_BHW.clone(), score_B
            continue
        better_B = score_B > best_score_B
        best_codes[better_B] = codes_BHW[better_B]
        best_score_B = torch.where(better_B, score_B, best_score_B)
    return best_codes

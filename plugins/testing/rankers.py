"""The contract of best-of-K rankers (:class:`~vqtouch.core.BestOfRanker`)."""

from __future__ import annotations

import inspect
from typing import Any

from vqtouch.core.components import BestOfRanker, BuildContext

from ._support import _require


def check_best_of_ranker(ranker: BestOfRanker, context: BuildContext | None = None, *, label: str = "ranker") -> None:
    """A best-of ranker says whether it ranks by class (``needs_classes``, a bool) and implements
    ``score(codes_BHW, batch)`` or ``choose(candidates_KBHW, batch)``, each taking those two arguments;
    ``prepare(pipeline)`` takes the pipeline.  (What a ranker chooses depends on a trained run, which
    the pipeline's tests exercise.)"""
    _require(isinstance(ranker.needs_classes, bool), label, f"needs_classes is {ranker.needs_classes!r}, not a bool")
    kind = type(ranker)
    _require(
        kind.score is not BestOfRanker.score or kind.choose is not BestOfRanker.choose,
        label,
        "implements neither score(codes_BHW, batch) nor choose(candidates_KBHW, batch)",
    )
    for name, arguments in (("score", 2), ("choose", 2), ("prepare", 1)):
        _require(
            _positional_count(getattr(ranker, name)) == arguments,
            label,
            f"{name} must take {arguments} argument{'s' if arguments > 1 else ''}",
        )


def _positional_count(method: Any) -> int | None:
    try:
        parameters = inspect.signature(method).parameters.values()
    except (TypeError, ValueError):
        return None
    return len([p for p in parameters if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)])

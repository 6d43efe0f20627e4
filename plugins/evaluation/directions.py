"""Which way is better for each score: the one place the report, the experiment tables and the
trade-off plots ask.

A metric plugin declares its own direction (``Metric.higher_is_better``); a run's report records
the directions of the metrics it built, and whoever renders scores of such a run does it inside
:func:`declared_directions`, so a new metric needs no edit here.  Scores that are not metric
plugins (losses, errors, the distribution scores the generation stage computes itself) follow the
built-in table below: :data:`LOWER_IS_BETTER` and the :data:`LOWER_IS_BETTER_SUFFIXES`; every
other score is higher-is-better.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Mapping
from contextvars import ContextVar

#: Scores (unprefixed names) where lower is better; every other score is taken as
#: higher-is-better.  Names ending in one of :data:`LOWER_IS_BETTER_SUFFIXES` are lower-is-better too.
LOWER_IS_BETTER = frozenset(
    {"mae", "mse", "loss", "contact_mae", "lpips", "fid", "kid", "fd_effnetlite0", "kid_effnetlite0"}
)
LOWER_IS_BETTER_SUFFIXES = ("_mae", "_loss", "_error_px")

#: The directions in force (:func:`declared_directions`): metric name -> "higher" or "lower".
_DECLARED: ContextVar[Mapping[str, str]] = ContextVar("declared_directions", default={})


@contextlib.contextmanager
def declared_directions(directions: Mapping[str, str]) -> Iterator[None]:
    """Within the block, ``directions`` (metric name -> ``"higher"`` or ``"lower"``, as a report
    records them from the metrics' ``higher_is_better``) decide the scores named after those
    metrics, with or without a prefix (``background_<name>``, ``zero_shot_<name>``), before the
    built-in table."""
    bad = {name: value for name, value in directions.items() if value not in ("higher", "lower")}
    if bad:
        raise ValueError(f"score directions must be 'higher' or 'lower', got {bad}")
    token = _DECLARED.set({**_DECLARED.get(), **directions})
    try:
        yield
    finally:
        _DECLARED.reset(token)


def metric_directions(metrics: Mapping[str, object]) -> dict[str, str]:
    """The direction each built metric declares (``higher_is_better``), by name: what a report records."""
    return {
        name: "higher" if getattr(metric, "higher_is_better", True) else "lower" for name, metric in metrics.items()
    }


def lower_is_better(score: str) -> bool:
    """Whether a lower value of ``score`` (an unprefixed result key such as ``contact_mae``) is better:
    a declared metric direction first (the longest metric name the score ends with), then
    :data:`LOWER_IS_BETTER`."""
    declared = _DECLARED.get()
    matches = [name for name in declared if score == name or score.endswith("_" + name)]
    if matches:
        return declared[max(matches, key=len)] == "lower"
    return score in LOWER_IS_BETTER or score.endswith(LOWER_IS_BETTER_SUFFIXES)


def direction_arrow(score: str) -> str:
    """``↓`` for a lower-is-better score, ``↑`` for the others."""
    return "↓" if lower_is_better(score) else "↑"


def shown_scores(scores: Mapping[str, object], shown: tuple[str, ...], metrics: list[str]) -> dict[str, object]:
    """The entries of a stage's ``scores`` its report shows: those in the stage's ``shown`` list, and
    those of the experiment's ``metrics`` (by name, with or without a prefix such as ``background_``),
    so that a metric plugin's scores reach the report like the built-ins'.  In ``scores``' order."""
    return {
        key: value
        for key, value in scores.items()
        if key in shown or any(key == name or key.endswith("_" + name) for name in metrics)
    }

"""Which way is better for each score: the one table the report, the experiment tables and the
trade-off plots read, in the evaluation library so that a new metric is declared here (or by its
name's suffix), never in core.

Every score not listed, and not ending in one of :data:`LOWER_IS_BETTER_SUFFIXES`, is higher-is-better.
"""

from __future__ import annotations

#: Scores (unprefixed names) where lower is better; every other score is taken as
#: higher-is-better.  Names ending in one of :data:`LOWER_IS_BETTER_SUFFIXES` are lower-is-better too.
LOWER_IS_BETTER = frozenset({"mae", "mse", "loss", "contact_mae", "lpips", "fid", "kid", "fd_effnetlite0",
                             "kid_effnetlite0"})
LOWER_IS_BETTER_SUFFIXES = ("_mae", "_loss", "_error_px")


def lower_is_better(score: str) -> bool:
    """Whether a lower value of ``score`` (an unprefixed result key such as ``contact_mae``) is better:
    see :data:`LOWER_IS_BETTER`."""
    return score in LOWER_IS_BETTER or score.endswith(LOWER_IS_BETTER_SUFFIXES)


def direction_arrow(score: str) -> str:
    """``↓`` for a lower-is-better score, ``↑`` for the others."""
    return "↓" if lower_is_better(score) else "↑"

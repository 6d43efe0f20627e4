"""The best-of-K rankers' plugin: the ``judge``, ``posterior`` and ``consensus`` rankers' options and
registration (the rankers, in judge.py, posterior.py and consensus.py, are imported when built), and
``--best-of-rank``'s help.

A ranker keeps one of the K candidates :func:`.best_of.sample_best_of` draws per condition; any plugin
adds one with ``vqtouch_register_best_of_rankers`` (a :class:`vqtouch.core.BestOfRanker`), and
``--best-of-rank NAME`` (``best_of_rank=`` on the pipeline) chooses it.
"""

from __future__ import annotations

from typing import Literal

from vqtouch.core import PluginConfig, hookimpl

#: The ranker of ``--best-of-rank`` when none is named.
DEFAULT_RANKER = "judge"


class JudgeRankerConfig(PluginConfig):
    """Options of the ``judge`` ranker (none besides its name)."""

    name: Literal["judge"] = "judge"


class PosteriorRankerConfig(PluginConfig):
    """Options of the ``posterior`` ranker (none besides its name)."""

    name: Literal["posterior"] = "posterior"


class ConsensusRankerConfig(PluginConfig):
    """Options of the ``consensus`` ranker (none besides its name)."""

    name: Literal["consensus"] = "consensus"


#: What each built-in ranker is, in words (its registration's description, the commands' help, the reports).
RANK_DESCRIPTIONS = {
    "judge": "a classifier of code grids fitted on the run's training codes",
    "posterior": "the generator's own class posterior",
    "consensus": "the candidate whose contact centre the others agree on most (any condition, no class)",
}
_JUDGE_COST = " (fitted once, about a minute)"
#: ``--best-of-rank``'s help, shared by every command that takes it.
BEST_OF_RANK_HELP = (
    "what ranks --best-of's candidates, a best_of_ranker plugin (`vqtouch plugins --kind best_of_ranker` "
    "lists those installed): "
    + "; ".join(
        f"{name} (default), {text}{_JUDGE_COST}" if name == DEFAULT_RANKER else f"{name}, {text}"
        for name, text in RANK_DESCRIPTIONS.items()
    )
)


def _sentence(text: str) -> str:
    return text[0].upper() + text[1:] + "."


@hookimpl
def vqtouch_register_best_of_rankers(register):
    """Register the three rankers."""
    register(
        "judge",
        "vqtouch.plugins.generator.judge:build_judge_ranker",
        JudgeRankerConfig,
        description=_sentence(RANK_DESCRIPTIONS["judge"]),
    )
    register(
        "posterior",
        "vqtouch.plugins.generator.posterior:build_posterior_ranker",
        PosteriorRankerConfig,
        description=_sentence(RANK_DESCRIPTIONS["posterior"]),
    )
    register(
        "consensus",
        "vqtouch.plugins.generator.consensus:build_consensus_ranker",
        ConsensusRankerConfig,
        description=_sentence(RANK_DESCRIPTIONS["consensus"]),
    )

"""Generator stage: the discrete-diffusion decoder over the tokenizer's code grid, its samplers, training and
generation.

The public API other packages use (imported on first use, so importing this package stays light):
generation from a trained run or a bundle (:func:`load_pipeline`, :func:`generator_tokenizer`,
:data:`GENERATOR_CHECKPOINTS`, where a run keeps the generator's checkpoints,
:func:`sample_images`, :func:`check_best_of` and :func:`check_best_of_rank` for its ``best_of`` and
the registered best-of ranker that ranks it, :data:`RANK_DESCRIPTIONS` (the built-in rankers) and
:data:`BEST_OF_RANK_HELP`),
scoring generated samples against held-out conditions (:func:`score_generation`,
:func:`held_out_conditions`, :func:`baseline_pool`, with :data:`GENERATION_SHOWN_SCORES` and
:data:`SAMPLES_CAPTION` for reports), and the sampling
speed/quality sweep of ``vqtouch tradeoff generator``, which ``vqtouch evaluate tradeoff`` runs too
(:func:`sweep_settings`, :func:`measure`, :func:`check_settings`, :func:`load_tradeoff_bench`,
:func:`pareto_front`, :func:`synchronize`).  Other packages import
these names from here, never the modules behind them (``make lint`` checks it).
"""

from __future__ import annotations

import importlib
from typing import Any

#: Public name -> (module of this package, name there).
_PUBLIC = {
    "GenerationPipeline": ("pipeline", "GenerationPipeline"),
    "load_pipeline": ("pipeline", "load_pipeline"),
    "generator_tokenizer": ("pipeline", "generator_tokenizer"),
    "GENERATOR_CHECKPOINTS": ("stage", "CHECKPOINT_FOLDER"),
    "sample_images": ("scoring", "sample_images"),
    "sampling_precision": ("scoring", "sampling_precision"),
    "check_condition_keys": ("stage", "check_condition_keys"),
    "check_best_of": ("best_of", "check_best_of"),
    "check_best_of_rank": ("best_of", "check_best_of_rank"),
    "refuse_idle_rank": ("best_of", "refuse_idle_rank"),
    "BEST_OF_RANK_HELP": ("rankers_plugin", "BEST_OF_RANK_HELP"),
    "RANK_DESCRIPTIONS": ("rankers_plugin", "RANK_DESCRIPTIONS"),
    "score_generation": ("scoring", "score_generation"),
    "held_out_conditions": ("scoring", "held_out_conditions"),
    "baseline_pool": ("scoring", "baseline_pool"),
    "GENERATION_SHOWN_SCORES": ("stage", "SHOWN_SCORES"),
    "SAMPLES_CAPTION": ("stage", "SAMPLES_CAPTION"),
    "fine_tune_for_sensor": ("sensor_finetune", "fine_tune_for_sensor"),
    "sweep_settings": ("tradeoff", "sweep_settings"),
    "measure": ("tradeoff", "measure"),
    "check_settings": ("tradeoff", "check_settings"),
    "load_tradeoff_bench": ("tradeoff", "load_tradeoff_bench"),
    "pareto_front": ("tradeoff", "pareto_front"),
    "synchronize": ("tradeoff", "synchronize"),
}

__all__ = sorted(_PUBLIC)


def __getattr__(name: str) -> Any:
    if name not in _PUBLIC:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    module, attribute = _PUBLIC[name]
    value = getattr(importlib.import_module(f"{__name__}.{module}"), attribute)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_PUBLIC])

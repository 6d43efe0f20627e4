"""``vqtouch evaluate tradeoff``'s plugin: its options and registration (the experiment, in
pipeline_tradeoff.py, is imported when the command runs)."""

from __future__ import annotations

import argparse
from typing import Any

from vqtouch.core import hookimpl
from vqtouch.plugins.cli.app import add_config_arguments, command_group, positive_int
from vqtouch.plugins.evaluation.records import add_experiment_arguments

from .pipeline_tradeoff_knobs import known_knobs

# Defaults of the full command and of --quick: (tokenizer steps, generator steps, rounds, timing steps, n).
STANDARD = {"tokenizer_steps": 150, "generator_steps": 300, "rounds": 3, "timing_steps": 3, "n": 32}
QUICK = {"tokenizer_steps": 40, "generator_steps": 60, "rounds": 2, "timing_steps": 2, "n": 16}
QUICK_KNOBS = ["deformable", "codebook", "precision", "steps", "sampler"]


@hookimpl
def vqtouch_add_commands(subparsers: Any) -> None:
    evaluate = command_group(subparsers, "evaluate", "evaluate a trained component")
    parser = evaluate.add_parser(
        "tradeoff",
        help="the whole pipeline's speed/accuracy trade: tokenizer and generator knobs, one table, "
        "Pareto plots (JSON, markdown, PNG)",
        description="Train a tokenizer per tokenizer knob value and a generator on the baseline tokenizer, time them "
        "in interleaved rounds and score them on the held-out split (contact region and no-contact "
        f"background included).  Default ({STANDARD['tokenizer_steps']} tokenizer steps, every knob, "
        "3 seeds): about 1 h on a quiet 2-core CPU, 3 h on a shared one; --quick: about 15 min quiet, "
        "40 min shared.  On a CPU without bf16 units the precision knob alone trains about 15 times "
        "slower (16 to 25 min per seed measured on a shared 2-core CPU at --quick): leave it out with "
        "--knobs deformable codebook steps sampler.  On a shared CPU give --threads 1.",
    )
    add_config_arguments(parser, scene_required=True)
    parser.set_defaults(scene_required=False)  # the default scene is filled in by the command
    add_experiment_arguments(parser)
    parser.add_argument(
        "--knobs",
        nargs="+",
        metavar="KNOB[=V1,V2]",
        help=f"knobs to measure, each at its default values or the ones given (known: "
        f"{known_knobs()}; default: every knob of the parts the scene trains)",
    )
    parser.add_argument(
        "--tokenizer-steps",
        type=positive_int,
        help=f"training steps of every tokenizer (default {STANDARD['tokenizer_steps']}, "
        f"--quick {QUICK['tokenizer_steps']})",
    )
    parser.add_argument(
        "--generator-steps",
        type=positive_int,
        help=f"training steps of the generator (default {STANDARD['generator_steps']}, "
        f"--quick {QUICK['generator_steps']})",
    )
    parser.add_argument(
        "--rounds",
        type=positive_int,
        help=f"interleaved timing rounds, the median kept (default {STANDARD['rounds']}, --quick {QUICK['rounds']})",
    )
    parser.add_argument(
        "--timing-steps",
        type=positive_int,
        help=f"training steps per tokenizer per timing round (default {STANDARD['timing_steps']}, "
        f"--quick {QUICK['timing_steps']})",
    )
    parser.add_argument(
        "--n",
        type=positive_int,
        help=f"held-out conditions each sampling setting generates (at most "
        f"the held-out split; default {STANDARD['n']}, --quick "
        f"{QUICK['n']})",
    )
    parser.add_argument("--batch-size", type=positive_int, default=16, help="conditions sampled at once (default 16)")
    parser.add_argument(
        "--distribution",
        action="store_true",
        help="also score every sampling setting's fd_effnetlite0 and classifier accuracy (slower)",
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help=f"small defaults: {QUICK['tokenizer_steps']} tokenizer and {QUICK['generator_steps']} "
        f"generator steps, {QUICK['rounds']} rounds, knobs {' '.join(QUICK_KNOBS)}",
    )
    parser.add_argument(
        "--full",
        action="store_true",
        help="keep the scene's model and data sizes (default: scaled down like `vqtouch demo`)",
    )
    # The same option as `vqtouch --threads` (either place; SUPPRESS keeps the global one's value).
    parser.add_argument(
        "--threads", type=positive_int, default=argparse.SUPPRESS, help="torch CPU threads (as vqtouch --threads)"
    )
    parser.set_defaults(handler="vqtouch.plugins.experiments.pipeline_tradeoff:_command")

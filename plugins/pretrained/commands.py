"""``vqtouch pretrained list`` and ``vqtouch pretrained export``.

::

    vqtouch pretrained list [--json]
    vqtouch pretrained export --run RUN --name tour [--precision fp16|fp32] [--weights ema|raw]
                              [--overwrite] [--root DIR]

``export`` writes a trained generator run's newest checkpoint, with the tokenizer it learned the
codes of, as a bundle inside the package (:mod:`.bundle`); the tour scene's ``pretrained`` stage
then shows it in every demo report.  A tokenizer run gives a tokenizer bundle, which every command
that reads a tokenizer takes as ``pretrained:NAME``.  ``list`` names each part's shipped recipe (the
config file ``vqtouch train ... --config`` reproduces it with) when it was trained from one.
"""

from __future__ import annotations

import argparse

from vqtouch.core import hookimpl
from vqtouch.plugins.cli.app import command_group


@hookimpl
def vqtouch_add_commands(subparsers):
    group = command_group(subparsers, "pretrained", "list the bundled pretrained checkpoints, or bundle a trained run")
    listing = group.add_parser("list", help="the bundled checkpoints, their steps, sizes and training commands")
    listing.add_argument("--json", action="store_true", help="machine-readable output")
    listing.add_argument("--root", help=argparse.SUPPRESS)
    listing.set_defaults(handler="vqtouch.plugins.pretrained.command_handlers:cmd_list")
    export = group.add_parser(
        "export", help="write a trained generator run (and its tokenizer), or a tokenizer run alone, as a bundle"
    )
    export.add_argument(
        "--run", required=True, help="a run whose generator stage trained, or a tokenizer run (a tokenizer bundle)"
    )
    export.add_argument("--name", required=True, help="the bundle's name (the pretrained stage's `bundle` option)")
    export.add_argument(
        "--precision",
        choices=("fp16", "fp32"),
        default="fp16",
        help="stored precision of the parameters (the quantizer's stay fp32; default fp16)",
    )
    export.add_argument("--overwrite", action="store_true", help="replace a bundle of that name")
    export.add_argument(
        "--sampling",
        action="append",
        default=[],
        metavar="KEY=JSON",
        help="a sampling default of the bundle instead of the run's (steps, guidance, truncation, "
        "conditioner_guidance), e.g. 'conditioner_guidance={\"label\": 2}' (repeatable)",
    )
    export.add_argument(
        "--weights",
        choices=("ema", "raw"),
        help="which of the run's weights to bundle: the moving average training kept (ema) or the raw "
        "ones (default: the run's generator.sample_weights, EMA when the checkpoint holds one)",
    )
    export.add_argument(
        "--root", help="folder of the bundles (default: the package's own, where the pretrained stage looks)"
    )
    export.set_defaults(handler="vqtouch.plugins.pretrained.command_handlers:cmd_export", output_options=("root",))

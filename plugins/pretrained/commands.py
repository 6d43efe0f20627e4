"""``vqtouch pretrained list`` and ``vqtouch pretrained export``.

::

    vqtouch pretrained list [--json]
    vqtouch pretrained export --run GENERATOR_RUN --name tour [--precision fp16|fp32] [--overwrite] [--root DIR]

``export`` writes a trained generator run's newest checkpoint, with the tokenizer it learned the
codes of, as a bundle inside the package (:mod:`.bundle`); the tour scene's ``pretrained`` stage
then shows it in every demo report.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from vqtouch.core import hookimpl
from vqtouch.core.cli import command_group

from .bundle import BUNDLES, bundle_names, describe_bundle, export_bundle


def _list_command(args: argparse.Namespace) -> int:
    root = Path(args.root) if args.root else BUNDLES
    rows = [describe_bundle(root / name) for name in bundle_names(root)]
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    if not rows:
        print(f"no bundled checkpoints in {root}")
        return 0
    for row in rows:
        print(
            f"{row['name']}: {row['tokenizer']} tokenizer step {row['tokenizer_step']}, generator step "
            f"{row['generator_step']} with conditioners {', '.join(row['conditioners'])}; {row['files']} files, "
            f"{row['megabytes']} MB ({row['stored_as']}, {row['weights']} weights)"
        )
        print(f"  tokenizer trained by: {row['tokenizer_command']}")
        print(f"  generator trained by: {row['generator_command']}")
    return 0


def _export_command(args: argparse.Namespace) -> int:
    folder = export_bundle(
        args.run,
        args.name,
        args.host,
        root=Path(args.root) if args.root else None,
        precision=args.precision,
        overwrite=args.overwrite,
    )
    row = describe_bundle(folder)
    print(
        f"bundle {row['name']!r} -> {folder} ({row['files']} files, {row['megabytes']} MB, {row['stored_as']}, "
        f"{row['weights']} weights; "
        f"tokenizer step {row['tokenizer_step']}, generator step {row['generator_step']})"
    )
    return 0


@hookimpl
def vqtouch_add_commands(subparsers):
    group = command_group(subparsers, "pretrained", "list the bundled pretrained checkpoints, or bundle a trained run")
    listing = group.add_parser("list", help="the bundled checkpoints, their steps, sizes and training commands")
    listing.add_argument("--json", action="store_true", help="machine-readable output")
    listing.add_argument("--root", help=argparse.SUPPRESS)
    listing.set_defaults(handler=_list_command)
    export = group.add_parser("export", help="write a trained generator run (and its tokenizer) as a bundle")
    export.add_argument("--run", required=True, help="a run whose generator stage trained")
    export.add_argument("--name", required=True, help="the bundle's name (the pretrained stage's `bundle` option)")
    export.add_argument(
        "--precision",
        choices=("fp16", "fp32"),
        default="fp16",
        help="stored precision of the parameters (the quantizer's stay fp32; default fp16)",
    )
    export.add_argument("--overwrite", action="store_true", help="replace a bundle of that name")
    export.add_argument(
        "--root", help="folder of the bundles (default: the package's own, where the pretrained stage looks)"
    )
    export.set_defaults(handler=_export_command)

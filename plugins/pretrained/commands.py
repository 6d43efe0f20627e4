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
import json
from pathlib import Path

from vqtouch.core import ConfigError, hookimpl
from vqtouch.core.cli import command_group

from . import bundle
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
        _print_bundle(row)
    return 0


def _print_bundle(row: dict) -> None:
    size = f"{row['files']} files, {row['megabytes']} MB"
    if row["kind"] == "tokenizer":
        print(
            f"{row['name']}: {row['tokenizer']} tokenizer step {row['tokenizer_step']} (a tokenizer bundle); "
            f"{size} ({row['stored_as']})"
        )
    else:
        print(
            f"{row['name']}: {row['tokenizer']} tokenizer step {row['tokenizer_step']}, generator step "
            f"{row['generator_step']} with conditioners {', '.join(row['conditioners'])}; {size} "
            f"({row['stored_as']}, {row['weights']} weights)"
        )
    parts = ("tokenizer", "generator") if row["kind"] == "generator" else ("tokenizer",)
    for part in parts:
        recipe = row["recipes"][part]
        print(
            f"  {part} recipe: "
            + (f"{recipe} (vqtouch train {part} --config {bundle.RECIPES / recipe})" if recipe else "none shipped")
        )
        print(f"  {part} trained by: {row[part + '_command']}")
    trained_in = {part: row["trained_in"][part] or "not recorded" for part in parts}
    print("  trained in: " + ", ".join(f"{part} {trained_in[part]}" for part in parts))
    if row["sampling_defaults"]:
        print(f"  sampling defaults set at export: {json.dumps(row['sampling_defaults'], sort_keys=True)}")


def _export_command(args: argparse.Namespace) -> int:
    sampling = {}
    for item in args.sampling:
        key, equals, text = item.partition("=")
        try:
            if not equals:
                raise ValueError("no '='")
            sampling[key.strip()] = json.loads(text)
        except ValueError as exc:
            raise ConfigError(f"--sampling {item!r}: give KEY=JSON, e.g. guidance=2 ({exc})") from None
    folder = export_bundle(
        args.run,
        args.name,
        args.host,
        root=Path(args.root) if args.root else None,
        precision=args.precision,
        overwrite=args.overwrite,
        sampling=sampling,
        weights=args.weights,
    )
    row = describe_bundle(folder)
    parts = f"tokenizer step {row['tokenizer_step']}"
    if row["kind"] == "generator":
        parts += f", {row['weights']} weights, generator step {row['generator_step']}"
    else:
        parts += ", a tokenizer bundle"
    print(
        f"bundle {row['name']!r} -> {folder} ({row['files']} files, {row['megabytes']} MB, {row['stored_as']}; {parts})"
    )
    return 0


@hookimpl
def vqtouch_add_commands(subparsers):
    group = command_group(subparsers, "pretrained", "list the bundled pretrained checkpoints, or bundle a trained run")
    listing = group.add_parser("list", help="the bundled checkpoints, their steps, sizes and training commands")
    listing.add_argument("--json", action="store_true", help="machine-readable output")
    listing.add_argument("--root", help=argparse.SUPPRESS)
    listing.set_defaults(handler=_list_command)
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
    export.set_defaults(handler=_export_command, output_options=("root",))

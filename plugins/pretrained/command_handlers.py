"""``vqtouch pretrained list`` and ``vqtouch pretrained export``: the handlers (their parsers are in commands.py)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from vqtouch.core import ConfigError

from . import bundle
from .bundle import BUNDLES, bundle_names, describe_bundle, export_bundle


def cmd_list(args: argparse.Namespace) -> int:
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


def cmd_export(args: argparse.Namespace) -> int:
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

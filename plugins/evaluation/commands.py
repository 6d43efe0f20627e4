"""``vqtouch evaluate pairs``: score a folder of generated images against a folder of real ones.

    vqtouch evaluate pairs --generated OUT/ --real HCT/test/tactile/ --protocol published \\
        --lpips-weights vgg16-397923af.pth --out scores.json

Images are paired by id (the path below the folder, without extension), so ``a/0001.png`` is
scored against ``a/0001.jpg``.  The protocol (:mod:`.protocols`) fixes the size, the metrics and
their options; its name is written next to the numbers.  Metrics whose weights are missing are
listed as skipped with the file to provide.  This module builds the parser; the handler, which
loads and scores the images, is in :mod:`.command_handlers`.
"""

from __future__ import annotations

import importlib
from typing import Any

from vqtouch.core import hookimpl
from vqtouch.plugins.cli.app import add_overwrite_argument, add_image_folder_arguments, command_group

from .protocols import PROTOCOLS

#: The scoring functions that lived here, now in command_handlers.py (which imports torch): still
#: importable from this module, loaded on first use so that building the parser stays light.
_MOVED = ("images_by_id", "load_pairs", "evaluate_pairs")


def __getattr__(name: str) -> Any:
    if name not in _MOVED:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__package__}.command_handlers"), name)


@hookimpl
def vqtouch_add_commands(subparsers: Any) -> None:
    evaluate = command_group(subparsers, "evaluate", "evaluate a trained component")
    pairs = evaluate.add_parser(
        "pairs",
        help="score a folder of generated images against a folder of real ones, "
        "paired by file name, under a named protocol",
    )
    pairs.add_argument("--generated", required=True, help="folder of generated images (any depth)")
    pairs.add_argument("--real", required=True, help="folder of real images with the same relative names")
    pairs.add_argument(
        "--protocol",
        default="published",
        choices=sorted(PROTOCOLS),
        help="published: 512 px, LPIPS-VGG, SSIM, pooled PSNR (the papers' tables); default: "
        "vqtouch's own-size protocol (default: published)",
    )
    pairs.add_argument(
        "--lpips-weights",
        metavar="PATH",
        help="torchvision's vgg16-397923af.pth (else VQTOUCH_LPIPS_VGG or VQTOUCH_WEIGHTS_DIR; "
        "without it LPIPS is skipped)",
    )
    pairs.add_argument("--out", help="also write the result to this JSON file")
    add_overwrite_argument(pairs, ".")
    add_image_folder_arguments(pairs)
    pairs.set_defaults(handler="vqtouch.plugins.evaluation.command_handlers:cmd_evaluate_pairs")

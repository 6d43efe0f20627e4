"""``vqtouch data``: export procedural datasets and check the sensors against real frames.

- ``vqtouch data render --sensor gelsight_mini --n 500 --out DIR`` writes a browsable folder:
  ``tactile/<id>.png``, ``visual/<id>.png``, ``index.csv`` (``path,label,visual`` plus class,
  text, sensor and depth; readable by the ``image_folder`` dataset), ``classes.txt``,
  ``preview.png`` and ``render.json`` (the exact dataset config and the timing).
- ``vqtouch data fidelity --out DIR`` renders taxim's real GelSight / GelSight Mini ball
  presses, prints SSIM and PSNR against the real frames, and saves real | rendered pictures.
- ``vqtouch data leakage --dataset SPEC`` (or ``--train SPEC --test SPEC``) finds held-out images
  that have a near-duplicate in training (see :mod:`vqtouch.plugins.data.leakage`).

This module builds the parsers; the handlers, which import torch, are in :mod:`.command_handlers`.
"""

from __future__ import annotations

import argparse
from typing import Any

from vqtouch.core import ConfigError, hookimpl
from vqtouch.plugins.cli.app import (
    add_overwrite_argument,
    fraction,
    non_negative_float,
    non_negative_int,
    plugin_block,
    positive_int,
    seed_int,
)
from vqtouch.core.config import DataConfig, ExperimentConfig
from vqtouch.core.image_size import image_size_argument

from .leakage_defaults import COMPARE_SIZE, DEFAULT_THRESHOLD


def _sensor_argument(text: str) -> Any:
    """``--sensor`` takes a family name or a JSON object (family plus options and variant)."""
    try:
        return plugin_block(text, "--sensor")
    except ConfigError as exc:  # argparse's own one-line usage error, at parse time
        raise argparse.ArgumentTypeError(str(exc)) from None


@hookimpl
def vqtouch_add_commands(subparsers):
    data = subparsers.add_parser(
        "data", help="export procedural datasets; check sensors against real frames and splits for leakage"
    )
    data_sub = data.add_subparsers(dest="data_command", metavar="ACTION", required=True)
    _add_render_command(data_sub)
    _add_fidelity_command(data_sub)
    _add_leakage_command(data_sub)


def _add_render_command(data_sub) -> None:
    render = data_sub.add_parser("render", help="render procedural (tactile, visual, label, text) samples to a folder")
    render.add_argument(
        "--sensor",
        type=_sensor_argument,
        default={"name": "gelsight"},
        help='sensor family name, or JSON such as \'{"name": "gelsight", "variant": {"noise_std": 0.02}}\'',
    )
    render.add_argument("--n", type=positive_int, default=500, help="number of samples (default 500)")
    render.add_argument("--out", required=True, help="output folder")
    render.add_argument(
        "--image-size",
        type=image_size_argument,
        default=64,
        help="image size: a side S, or HEIGHTxWIDTH such as 240x320 (default 64)",
    )
    render.add_argument("--seed", type=seed_int, default=0, help="dataset seed (default 0)")
    render.add_argument("--classes", help="comma-separated object classes (default: all 12)")
    render.add_argument("--batch-size", type=positive_int, default=32, help="samples rendered per step (default 32)")
    render.add_argument("--overwrite", action="store_true", help="allow writing into a non-empty folder")
    render.set_defaults(handler="vqtouch.plugins.data.command_handlers:cmd_render")


def _add_fidelity_command(data_sub) -> None:
    fidelity = data_sub.add_parser("fidelity", help="SSIM/PSNR of rendered vs real taxim ball presses, with pictures")
    fidelity.add_argument("--out", required=True, help="folder for the pictures and fidelity.json")
    add_overwrite_argument(fidelity, "fidelity.json")
    fidelity.add_argument(
        "--sensors",
        nargs="+",
        default=["gelsight", "gelsight_mini"],
        choices=["gelsight", "gelsight_mini"],
        help="sensors to check",
    )
    fidelity.add_argument("--height", type=positive_int, default=240, help="render height (width is 4/3 of it)")
    fidelity.add_argument("--crop", type=positive_int, default=64, help="side of the square crop around each contact")
    fidelity.set_defaults(handler="vqtouch.plugins.data.command_handlers:cmd_fidelity")


def _add_leakage_command(data_sub) -> None:
    leakage = data_sub.add_parser(
        "leakage",
        help="held-out images with a near-duplicate in training (e.g. frames of one recording)",
        description="For each test image, its nearest train image by mean absolute pixel difference at a small "
        "size; pairs within --threshold are near-duplicates. Check the split an experiment makes "
        "(--dataset) or two datasets (--train, --test). Exits 0 (a report) unless --fail-above is "
        "exceeded (1) or an input is bad (2).",
    )
    leakage.add_argument(
        "--dataset",
        metavar="SPEC",
        help="dataset whose train/held-out split (as every stage makes it) is checked: a dataset "
        'plugin name, or JSON such as \'{"name": "touch_and_go", "root": "/data/tag"}\'',
    )
    leakage.add_argument("--train", metavar="SPEC", help="training dataset (name or JSON), with --test")
    leakage.add_argument("--test", metavar="SPEC", help="test dataset (name or JSON), with --train")
    leakage.add_argument(
        "--val-fraction",
        type=fraction,
        default=DataConfig.model_fields["val_fraction"].default,
        help="held-out share of --dataset's split (default: data.val_fraction's default, %(default)s)",
    )
    leakage.add_argument(
        "--seed",
        type=seed_int,
        default=ExperimentConfig.model_fields["seed"].default,
        help="experiment seed of --dataset's split (default %(default)s)",
    )
    leakage.add_argument(
        "--sensor",
        type=_sensor_argument,
        default={"name": "gelsight"},
        help="sensor family (name or JSON, as for render) of datasets that render, such as "
        "procedural (default gelsight)",
    )
    leakage.add_argument(
        "--threshold",
        type=non_negative_float,
        default=DEFAULT_THRESHOLD,
        help="near-duplicate when the mean absolute difference is at most this, in 8-bit levels "
        "(default %(default)s; raise it above a noisy sensor's noise floor)",
    )
    leakage.add_argument(
        "--size",
        type=positive_int,
        default=COMPARE_SIZE,
        help="side of the square images are compared at (default %(default)s)",
    )
    leakage.add_argument(
        "--show", type=non_negative_int, default=8, help="closest pairs listed and pictured (default 8)"
    )
    leakage.add_argument("--out", help="folder for leakage.json and closest_pairs.png")
    add_overwrite_argument(leakage, "leakage.json")
    leakage.add_argument(
        "--fail-above",
        type=fraction,
        metavar="FRACTION",
        help="exit with status 1 when more than this share of test images have a near-duplicate (for CI)",
    )
    leakage.set_defaults(handler="vqtouch.plugins.data.command_handlers:cmd_leakage")

"""``vqtouch train tokenizer``, ``vqtouch reconstruct`` and ``vqtouch evaluate reconstruction``: their parsers
(the handlers, in command_handlers.py, are imported when a command runs).

``train tokenizer`` runs the ``tokenizer`` stage (see :mod:`.stages`) through the same path as
``vqtouch demo``; the other two read a trained run.
"""

from __future__ import annotations

import argparse

from vqtouch.core import hookimpl
from vqtouch.plugins.cli.app import (
    add_overwrite_argument,
    add_config_arguments,
    add_image_folder_arguments,
    add_run_arguments,
    add_step_argument,
    NumberType,
    command_group,
    positive_int,
    seed_int,
)
from vqtouch.plugins.evaluation.records import DEFAULT_SEEDS

#: The MAE baseline's mask ratio, as its config allows it: [0, 1).
mask_ratio = NumberType(float, 0, 1, high_open=True, what="mask_ratio")


@hookimpl
def vqtouch_add_commands(subparsers):
    _add_train_tokenizer_command(subparsers)
    _add_reconstruct_command(subparsers)
    _add_evaluate_reconstruction_command(subparsers)


def _add_train_tokenizer_command(subparsers) -> None:
    train = command_group(subparsers, "train", "train a component (tokenizer, ...)")
    tokenizer = train.add_parser("tokenizer", help="train a tactile tokenizer (autoencoder + quantizer [+ GAN])")
    add_config_arguments(tokenizer, default_scene="reconstruction")
    add_run_arguments(tokenizer)
    tokenizer.set_defaults(handler="vqtouch.plugins.tokenizer.command_handlers:cmd_train_tokenizer")


def _add_reconstruct_command(subparsers) -> None:
    reconstruct = subparsers.add_parser("reconstruct", help="encode and decode images with a trained tokenizer")
    reconstruct.add_argument(
        "--run",
        required=True,
        help="run directory, a tokenizer checkpoint folder (e.g. an adapt output) or a bundle (pretrained:NAME)",
    )
    add_step_argument(reconstruct)
    source = reconstruct.add_mutually_exclusive_group(required=True)
    source.add_argument(
        "--real-frames",
        metavar="SENSOR",
        help="the real reference frames of this sensor family (name or JSON), e.g. gelsight",
    )
    source.add_argument(
        "--images",
        help="a sensor's image folder to reconstruct (images in it, class sub-folders, or a `vqtouch data "
        'render` export), or a JSON dataset block of any reader, e.g. \'{"name": "touch_and_go", '
        '"root": "data/tag"}\'',
    )
    reconstruct.add_argument(
        "--images-option",
        dest="images_options",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="an option of the --images reader (repeatable), e.g. max_samples=100 (--lenient and "
        "--allow-greyscale also set the reader's lenient and allow_greyscale)",
    )
    reconstruct.add_argument("--out", required=True, help="folder for reconstructions.png and reconstruct.json")
    add_overwrite_argument(reconstruct, "reconstruct.json")
    add_image_folder_arguments(reconstruct)
    reconstruct.set_defaults(handler="vqtouch.plugins.tokenizer.command_handlers:cmd_reconstruct")


def _add_evaluate_reconstruction_command(subparsers) -> None:
    evaluate = command_group(subparsers, "evaluate", "evaluate a trained component")
    recon = evaluate.add_parser(
        "reconstruction",
        help="score a trained tokenizer on the held-out split; with --out, "
        "the experiment: reconstruction against training-set size "
        "for each model over seeds (Table 1: JSON, markdown, PNG)",
    )
    mode = recon.add_mutually_exclusive_group(required=True)
    mode.add_argument(
        "--run",
        help="run directory of a trained tokenizer: score it (a tokenizer folder outside a run, e.g. a "
        "`vqtouch adapt` output, or a bundle, pretrained:NAME, with --dataset)",
    )
    mode.add_argument(
        "--out",
        help="run the experiment into this folder: train every model of --models and "
        "--mae-ratios on each --samples count of the scene's data, per seed",
    )
    _add_experiment_options(recon)
    add_config_arguments(recon, default_scene="reconstruction")
    add_step_argument(recon)
    recon.add_argument("--split", choices=["val", "all"], default="val", help="held-out split or all samples")
    recon.add_argument("--metrics", help="comma-separated metric plugins (default: the run's metrics)")
    recon.add_argument(
        "--dataset",
        help="evaluate on this dataset (JSON config, used whole) instead of the run's "
        'held-out split, e.g. \'{"name": "procedural", "seed": 999}\'',
    )
    recon.set_defaults(handler="vqtouch.plugins.tokenizer.command_handlers:cmd_evaluate_reconstruction")


def _add_experiment_options(recon) -> None:
    """The options of ``evaluate reconstruction --out``: the experiment's seeds, sizes and models."""
    recon.add_argument(
        "--seeds",
        type=seed_int,
        nargs="+",
        default=list(DEFAULT_SEEDS),
        help="with --out: seeds (split, sample draw, initialisation; default 0 1 2)",
    )
    recon.add_argument(
        "--samples",
        type=positive_int,
        nargs="+",
        default=[100, 1000, 10000],
        help="with --out: training-set sizes (default 100 1000 10000; the same steps for each)",
    )
    recon.add_argument(
        "--models",
        nargs="*",
        default=["vqgan", "dm_vqgan"],
        help="with --out: autoencoder plugins swapped into the scene's tokenizer (default vqgan dm_vqgan)",
    )
    recon.add_argument(
        "--mae-ratios",
        type=mask_ratio,
        nargs="*",
        default=[0.25, 0.5, 0.75],
        help="with --out: mask ratios of the MAE baseline (default 0.25 0.5 0.75; none: leave it out)",
    )
    recon.add_argument(
        "--held-out",
        type=positive_int,
        help="with --out: held-out procedural samples (default 200; a reader's dataset holds out "
        "data.val_fraction of its groups instead)",
    )
    recon.add_argument(
        "--distribution",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="with --out: also score fd_effnetlite0 (default: on)",
    )
    recon.add_argument(
        "--overwrite",
        action="store_true",
        help="with --out: write the result again (finished runs with an unchanged config are reused)",
    )

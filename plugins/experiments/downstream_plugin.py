"""``vqtouch evaluate downstream``'s plugin: its options and registration (the experiment, in
downstream.py, is imported when the command runs)."""

from __future__ import annotations

from typing import Any

from vqtouch.core import hookimpl
from vqtouch.plugins.cli.app import (
    NumberType,
    add_step_argument,
    command_group,
    guidance_scale,
    non_negative_int,
    positive_int,
)
from vqtouch.plugins.evaluation.records import add_experiment_arguments
from vqtouch.plugins.generator import BEST_OF_RANK_HELP

from .arguments import feature_size_argument

#: ``--generated-weight``: a finite number > 0.
generated_weight = NumberType(float, 0, low_open=True, what="generated_weight")


@hookimpl
def vqtouch_add_commands(subparsers: Any) -> None:
    evaluate = command_group(subparsers, "evaluate", "evaluate a trained component")
    downstream = evaluate.add_parser(
        "downstream",
        help="downstream recognition (Table 3): a classifier trained on generated, few real, both, or "
        "all real images, tested on the run's real held-out images (JSON, markdown, PNG)",
    )
    downstream.add_argument(
        "--run",
        required=True,
        help="a run whose generator trained with a label conditioner "
        "(e.g. `vqtouch train generator --scene label-to-touch`), "
        "or a bundle (pretrained:NAME)",
    )
    add_step_argument(downstream)
    add_experiment_arguments(downstream)
    downstream.add_argument(
        "--shots", type=positive_int, default=5, help="real training images per class of the few-shot arms (default 5)"
    )
    downstream.add_argument(
        "--generated-per-class", type=positive_int, default=10, help="images generated per class and seed (default 10)"
    )
    downstream.add_argument(
        "--conditioner",
        type=non_negative_int,
        help="which of the generator's conditioners (index; default the first label conditioner)",
    )
    downstream.add_argument("--steps", type=positive_int, help="sampling steps (default: the run's generator.steps)")
    downstream.add_argument("--sampler", help="sampler plugin (default: the run's generator.sampler)")
    downstream.add_argument(
        "--guidance", type=guidance_scale, help="classifier-free guidance scale (default: the run's)"
    )
    downstream.add_argument(
        "--feature-size",
        type=feature_size_argument,
        help="side EfficientNet-Lite0 sees the images at (default: the run's fd_effnetlite0 metric's, else 224)",
    )
    downstream.add_argument(
        "--train-images",
        type=non_negative_int,
        default=0,
        help="featurize at most this many real training images, drawn once at random (default 0: "
        "all; the ceiling arm trains on them)",
    )
    downstream.add_argument("--batch-size", type=positive_int, default=16, help="labels generated per forward pass")
    downstream.add_argument(
        "--generated-weight",
        type=generated_weight,
        nargs="+",
        default=[1.0],
        metavar="W",
        help="the `real few + generated` arm once per weight W: a generated image weighs W against 1 for a "
        "real one in the classifier's fit (default 1; e.g. 1 0.3 0.1 compares three in one run)",
    )
    downstream.add_argument(
        "--through-tokenizer",
        action="store_true",
        help="pass every real image (training and held-out) and the no-contact image through the run's "
        "tokenizer first, so that real and generated images share the decoder's look",
    )
    downstream.add_argument(
        "--best-of",
        type=positive_int,
        default=1,
        metavar="K",
        help="draw K candidates for every generated image and keep the one --best-of-rank finds "
        "most typical of its label (about K times the sampling time; default 1: plain sampling)",
    )
    downstream.add_argument(
        "--best-of-rank",
        metavar="RANKER",
        default="judge",
        help=BEST_OF_RANK_HELP,
    )
    downstream.set_defaults(handler="vqtouch.plugins.experiments.downstream:_evaluate_downstream_command")

"""``vqtouch train generator``, ``vqtouch generate``, ``vqtouch evaluate generation`` and
``vqtouch tradeoff generator`` (:mod:`.tradeoff`).

``train generator`` runs the scene's stages up to the generator in one run directory (the
tokenizer stage first, unless ``--tokenizer RUN`` names a trained one, whose tokenizer config is
then copied so the generator is built for its codes); ``generate`` writes images from a trained
run through :func:`.pipeline.load_pipeline`.
"""

from __future__ import annotations

import argparse
from typing import Any

from vqtouch.core import hookimpl
from vqtouch.plugins.cli.app import (
    add_overwrite_argument,
    add_greyscale_argument,
    add_config_arguments,
    add_run_arguments,
    add_step_argument,
    command_group,
    guidance_scale,
    non_negative_int,
    positive_int,
    seed_int,
    truncation_mass,
)

from .rankers_plugin import BEST_OF_RANK_HELP, DEFAULT_RANKER


def feature_size_argument(text: str) -> int:
    """``--feature-size``'s type, :func:`vqtouch.plugins.evaluation.feature_networks.feature_size_argument`,
    imported when the option is given: that module imports torch, which a parser must not (same name, so
    argparse's messages are the same)."""
    from vqtouch.plugins.evaluation.feature_networks import feature_size_argument as parse

    return parse(text)


def _add_weights_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--weights",
        choices=["ema", "raw"],
        help="sample with the moving average of the weights that training kept (ema) or the raw ones "
        "(default: the run's generator.sample_weights, EMA when the checkpoint holds one)",
    )


def _add_best_of_rank_argument(parser: argparse.ArgumentParser) -> None:
    """``--best-of-rank``, the ranking that keeps the best of ``--best-of`` candidates."""
    parser.add_argument(
        "--best-of-rank",
        metavar="RANKER",
        default=DEFAULT_RANKER,
        help=BEST_OF_RANK_HELP,
    )


def _add_sampling_arguments(parser: argparse.ArgumentParser) -> None:
    """``--steps``, ``--sampler``, ``--guidance`` and ``--truncation``, each the run's when not given."""
    parser.add_argument("--steps", type=positive_int, help="sampling steps (default: the run's generator.steps)")
    parser.add_argument("--sampler", help="sampler plugin (default: the run's generator.sampler)")
    parser.add_argument(
        "--guidance",
        type=guidance_scale,
        help="classifier-free guidance scale (1: none; default: the run's for the conditioner)",
    )
    parser.add_argument(
        "--truncation", type=truncation_mass, help="keep the most likely codes holding this mass (1: all)"
    )


def _add_tradeoff_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of ``vqtouch tradeoff generator``."""
    parser.add_argument(
        "--run", required=True, help="a run whose generator stage trained, or a bundle (pretrained:NAME)"
    )
    parser.add_argument("--out", required=True, help="folder for tradeoff.json, tradeoff.md and pareto.png")
    add_overwrite_argument(parser, "tradeoff.json")
    parser.add_argument(
        "--conditioner",
        type=non_negative_int,
        default=0,
        help="which of the generator's conditioners generates (its index; default 0)",
    )
    parser.add_argument("--n", type=positive_int, default=64, help="held-out conditions per setting (at most all)")
    parser.add_argument("--rounds", type=positive_int, default=2, help="interleaved timing rounds (median reported)")
    _add_tradeoff_knob_arguments(parser)
    parser.add_argument(
        "--classifier-on",
        choices=["real", "reconstructions"],
        default="real",
        help="train the classifier-accuracy column's classifier on the real training images (default) or "
        "on the tokenizer's reconstructions of them, which judges decoded images fairly",
    )
    parser.add_argument("--batch-size", type=positive_int, default=16, help="conditions per forward pass")
    parser.add_argument(
        "--grid",
        action="store_true",
        help="every combination (default: one knob at a time around the first sampler, guidance and "
        "precision and the middle --steps value)",
    )
    parser.add_argument("--seed", type=seed_int, help="seed of the sampling draws (default: the run's)")
    # The same option as `vqtouch --threads` (either place; SUPPRESS keeps the global one's value).
    parser.add_argument(
        "--threads", type=positive_int, default=argparse.SUPPRESS, help="torch CPU threads (as vqtouch --threads)"
    )
    _add_distribution_arguments(parser)


def _add_tradeoff_knob_arguments(parser: argparse.ArgumentParser) -> None:
    """The values ``vqtouch tradeoff generator`` sweeps, knob by knob (the first of each is the base)."""
    parser.add_argument("--steps", type=positive_int, nargs="+", default=[100, 50, 25, 10, 5], help="sampling steps")
    parser.add_argument(
        "--samplers",
        nargs="+",
        default=["posterior", "purity", "confidence"],
        help="sampler plugins (the first is the base)",
    )
    parser.add_argument(
        "--guidance",
        type=guidance_scale,
        nargs="+",
        default=[1.0, 3.0],
        help="classifier-free guidance scales (1: unguided; the first is the base)",
    )
    parser.add_argument(
        "--precisions",
        nargs="+",
        default=["fp32", "bf16"],
        metavar="{fp32,bf16}",
        help="fp32, or bf16 autocast (the first is the base)",
    )
    parser.add_argument(
        "--best-of",
        type=positive_int,
        nargs="+",
        metavar="K",
        help="candidates per condition, the --best-of-rank's choice kept (label conditions, or any with "
        "--best-of-rank consensus; the first is the base; default: not a knob, one draw)",
    )
    _add_best_of_rank_argument(parser)


def _add_distribution_arguments(parser: argparse.ArgumentParser) -> None:
    """``--distribution/--no-distribution`` and ``--feature-size``, shared by ``evaluate generation``
    and ``tradeoff generator``."""
    parser.add_argument(
        "--distribution",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="also score fd_effnetlite0 against the real held-out images and the accuracy of a "
        "classifier trained on real training images (default: on)",
    )
    parser.add_argument(
        "--feature-size",
        type=feature_size_argument,
        help="side EfficientNet-Lite0 sees the images at (default: the run's fd_effnetlite0 metric's, else 224)",
    )


class _CountAction(argparse.Action):
    """``--n`` that remembers it was given (a single condition value is then repeated)."""

    def __call__(self, parser: Any, namespace: Any, values: Any, option_string: Any = None) -> None:
        setattr(namespace, self.dest, values)
        namespace.n_given = True


@hookimpl
def vqtouch_add_commands(subparsers):
    _add_train_generator(subparsers)
    _add_evaluate_generation(subparsers)
    _add_tradeoff_generator(subparsers)
    _add_generate(subparsers)


def _add_train_generator(subparsers: Any) -> None:
    """``vqtouch train generator``."""
    train = command_group(subparsers, "train", "train a component (tokenizer, ...)")
    generator = train.add_parser(
        "generator",
        help="train a discrete-diffusion generator over a tokenizer's codes "
        "(trains the tokenizer first unless --tokenizer is given)",
    )
    add_config_arguments(generator, default_scene="label-to-touch")
    add_run_arguments(generator)
    generator.add_argument(
        "--tokenizer",
        metavar="RUN",
        help="learn the codes of this tokenizer: a run, a checkpoint folder (e.g. an adapt output) or a bundle "
        "(pretrained:NAME)",
    )
    generator.set_defaults(handler="vqtouch.plugins.generator.command_handlers:cmd_train_generator")


def _add_evaluate_generation(subparsers: Any) -> None:
    """``vqtouch evaluate generation``: score one run (``--run``) or run the experiment (``--out``)."""
    evaluate = command_group(subparsers, "evaluate", "evaluate a trained component")
    scored = evaluate.add_parser(
        "generation",
        help="generate the run's held-out conditions and score them against "
        "their ground truth, the no-contact background and the contact "
        "region; with --out, the per-conditioner experiment over seeds "
        "(Table 2: JSON, markdown, PNG)",
    )
    _add_scored_target_arguments(scored)
    add_config_arguments(scored, default_scene="tour")
    add_step_argument(scored)
    _add_weights_argument(scored)
    scored.add_argument(
        "--conditioner", type=non_negative_int, help="which of the generator's conditioners (index; default 0)"
    )
    scored.add_argument("--n", type=positive_int, default=64, help="held-out conditions to generate (at most all)")
    _add_sampling_arguments(scored)
    scored.add_argument("--seed", type=seed_int, help="seed of the sampling draws (default: the run's)")
    _add_metric_arguments(scored)
    _add_distribution_arguments(scored)
    scored.add_argument(
        "--best-of",
        type=positive_int,
        default=1,
        metavar="K",
        help="draw K candidates per condition and keep --best-of-rank's choice (about K times the time of one "
        "draw; 1: plain sampling); with every conditioner scored and a class ranking, conditioners without "
        "classes draw once",
    )
    _add_best_of_rank_argument(scored)
    scored.add_argument(
        "--classifier-on",
        choices=["real", "reconstructions"],
        default="real",
        help="with --run: train the distribution scores' classifier on the real training images "
        "(default) or on the tokenizer's reconstructions of them, which judges decoded images "
        "(samples and the tokenizer's ceiling) fairly",
    )
    scored.set_defaults(handler="vqtouch.plugins.generator.command_handlers:cmd_evaluate_generation")


def _add_scored_target_arguments(parser: argparse.ArgumentParser) -> None:
    """What ``evaluate generation`` scores: a run (``--run``), or the experiment's folder and its options."""
    parser.add_argument(
        "--run",
        help="a run whose generator stage trained, or a bundle (pretrained:NAME): score it "
        "(with --out DIR, into DIR/generation.json; a bundle is read-only and needs "
        "--out)",
    )
    parser.add_argument(
        "--out",
        help="without --run: run the experiment into this folder: train the scene's "
        "generator once per seed over one tokenizer and score every conditioner against "
        "the baselines; with --run: where the run's scores go",
    )
    parser.add_argument(
        "--seeds", type=seed_int, nargs="+", default=[0, 1, 2], help="with --out: generator seeds (default 0 1 2)"
    )
    parser.add_argument(
        "--tokenizer",
        metavar="RUN",
        help="with --out: the trained tokenizer every seed's generator "
        "learns (default: the scene's, trained once into OUT/tokenizer)",
    )
    parser.add_argument(
        "--overwrite", action="store_true", help="with --out: run again into a folder that holds an earlier result"
    )


def _add_metric_arguments(parser: argparse.ArgumentParser) -> None:
    """``--metrics`` and the CLIP score's ``--clip-checkpoint`` and ``--clip-architecture``."""
    parser.add_argument(
        "--metrics",
        help="comma-separated metric plugins, or a JSON list of names and "
        '{"name": ..., options} blocks (default: the run\'s metrics)',
    )
    parser.add_argument(
        "--clip-checkpoint",
        metavar="PATH",
        help="open_clip weights file of the clip_score metric (CLIP-space agreement of each "
        "generated image with its condition), added to the metrics; a clip_score listed "
        "without it reads VQTOUCH_CLIP_CKPT or VQTOUCH_WEIGHTS_DIR, else is reported as skipped",
    )
    parser.add_argument(
        "--clip-architecture",
        metavar="NAME",
        help="open_clip model name the --clip-checkpoint file holds (default: ViT-B-32)",
    )


def _add_tradeoff_generator(subparsers: Any) -> None:
    """``vqtouch tradeoff generator``."""
    tradeoff = command_group(subparsers, "tradeoff", "measure the speed/quality trade-off of a trained component")
    traded = tradeoff.add_parser(
        "generator",
        help="time and score a trained generator at each sampler, steps, "
        "guidance and precision setting (tradeoff.json, tradeoff.md, "
        "pareto.png)",
    )
    _add_tradeoff_arguments(traded)
    add_step_argument(traded)
    traded.set_defaults(handler="vqtouch.plugins.generator.command_handlers:cmd_tradeoff_generator")


def _add_generate(subparsers: Any) -> None:
    """``vqtouch generate``."""
    generate = subparsers.add_parser("generate", help="generate tactile images with a trained generator run")
    generate.add_argument(
        "--run", required=True, help="a run whose generator stage trained, or a bundle (pretrained:NAME)"
    )
    add_step_argument(generate)
    _add_weights_argument(generate)
    _add_condition_arguments(generate)
    _add_sampling_arguments(generate)
    generate.add_argument("--seed", type=seed_int, default=0, help="seed: same seed and settings, same images")
    generate.add_argument("--batch-size", type=positive_int, default=16, help="images per forward pass")
    generate.add_argument(
        "--best-of",
        type=positive_int,
        default=1,
        metavar="K",
        help="draw K candidates per image and keep --best-of-rank's choice (a label condition, or any with "
        "--best-of-rank consensus; about K times the time of one draw; default 1: plain sampling)",
    )
    _add_best_of_rank_argument(generate)
    generate.add_argument(
        "--out", required=True, help="folder for sample_*.png, grid.png and generate.json (written whole, at the end)"
    )
    generate.add_argument("--overwrite", action="store_true", help="replace what --out holds")
    add_greyscale_argument(generate)
    generate.set_defaults(handler="vqtouch.plugins.generator.command_handlers:cmd_generate", n_given=False)


def _add_condition_arguments(parser: argparse.ArgumentParser) -> None:
    """``generate``'s conditions, the conditioner that encodes them and how many images they draw."""
    parser.add_argument("--label", action="append", help="class index or name (repeatable: one per image)")
    parser.add_argument("--visual", action="append", metavar="IMG", help="visual image file (repeatable)")
    parser.add_argument("--tactile", action="append", metavar="IMG", help="conditioning tactile image (repeatable)")
    parser.add_argument("--text", action="append", help="text description (repeatable)")
    parser.add_argument(
        "--condition",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a condition a third-party conditioner reads (sample key = value)",
    )
    parser.add_argument(
        "--conditioner",
        metavar="INDEX|NAME",
        help="which of the generator's conditioners encodes the condition (index or name, e.g. "
        "1 or visual); needed only when several read the same kind of condition",
    )
    parser.add_argument(
        "--n",
        type=positive_int,
        default=1,
        action=_CountAction,
        help="number of images (a single condition value is repeated)",
    )

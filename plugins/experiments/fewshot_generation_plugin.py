"""``vqtouch fewshot``'s plugin: the ``fewshot`` stage's section, the commands' options and their registration
(the experiments, in fewshot_generation.py and fewshot_table.py, are imported when they run)."""

from __future__ import annotations

import argparse
from typing import Any, Literal

from pydantic import Field

from vqtouch.core import Section, hookimpl
from vqtouch.plugins.cli.app import (
    add_image_folder_arguments,
    command_group,
    family_ratio,
    non_negative_float,
    non_negative_int,
    positive_int,
)
from vqtouch.plugins.adaptation import AdaptSettings
from vqtouch.plugins.evaluation.records import add_experiment_arguments

from .arguments import feature_size_argument

#: Where the ``fewshot`` stage writes, inside its run.
FEWSHOT_FOLDER = "fewshot"


class FewshotSection(Section):
    """The ``fewshot`` stage's section: few-shot generation for the experiment's target sensor.  The
    shots, the ratio, the adaptation steps and the held-out images are the ``adapt`` section's, so the
    stage reuses the ``adapt`` stage's tokenizer when it adapted the same family tokenizer."""

    family_generator: str | None = Field(
        None,
        description="The family's generator: null, this run's own (its generator stage); pretrained:NAME, a "
        "bundle (the tour demo's: a generator trained for demo minutes draws too little to adapt).",
    )
    tokenizer_part: Literal["all", "decoder"] = Field(
        "decoder",
        description="What adapting the tokenizer fine-tunes: the decoder alone (every image keeps its codes, "
        "so the family generator's still fit; measured better) or all of it.  The adapt stage's tokenizer is "
        "reused when it was adapted the same way from the same tokenizer.",
    )
    rebase: bool = Field(
        True,
        description="Re-base the sensor's images onto the family's no-contact image for its tokenizer, so a "
        "contact keeps its family codes and the family generator's codes decode in the sensor's look.",
    )
    generator_steps: int = Field(300, ge=1, le=1_000_000, strict=True, description="Generator fine-tuning steps.")
    samples: int = Field(16, ge=1, le=100_000, strict=True, description="Images generated per condition and arm.")
    feature_size: int = Field(224, ge=32, le=1024, strict=True, description="Side EfficientNet-Lite0 sees images at.")
    score: bool = Field(True, description="Score the samples' fd_effnetlite0 against the target's held-out images.")


@hookimpl
def vqtouch_register_stages(register: Any) -> None:
    register(
        "fewshot",
        "vqtouch.plugins.experiments.fewshot_generation:run_fewshot_stage",
        section=FewshotSection,
        needs=("target_sensor",),
        makes=("fewshot_generator",),
        demo={"generator_steps": 60, "samples": 8, "feature_size": 64},
        trains="generator_steps",
        description="Generate images of the unseen target sensor: adapt the tokenizer, fine-tune the family "
        "generator on its shots mixed with family data, sample every condition.",
    )


#: The options :func:`_add_fewshot_arguments` adds beside --run and --images, as keyword arguments.
FEWSHOT_OPTIONS = (
    "shots",
    "tokenizer_steps",
    "tokenizer_part",
    "rebase",
    "generator_steps",
    "families",
    "family",
    "threshold",
    "samples",
    "eval_images",
    "feature_size",
)


def _add_fewshot_arguments(parser: argparse.ArgumentParser) -> None:
    """The options `vqtouch fewshot` and `vqtouch evaluate fewshot-generation` share."""
    parser.add_argument(
        "--run",
        required=True,
        help="the sensor family's generator: a run (vqtouch train generator) or a bundle (pretrained:tour)",
    )
    parser.add_argument(
        "--images",
        required=True,
        help="a folder of the unseen sensor's images (flat, class sub-folders or an index.csv), or a registered "
        "sensor (name or JSON variant) to render them",
    )
    parser.add_argument(
        "--shots", type=positive_int, default=50, help="images of the new sensor to learn from (default 50)"
    )
    parser.add_argument("--tokenizer-steps", type=positive_int, default=200, help="adaptation steps (default 200)")
    parser.add_argument(
        "--tokenizer-part",
        choices=("all", "decoder"),
        default="decoder",
        help="what adaptation fine-tunes: the decoder alone (default: every image keeps its codes, so the "
        "family generator's still fit; measured better) or all of it",
    )
    parser.add_argument(
        "--no-rebase",
        dest="rebase",
        action="store_false",
        help="encode the sensor's images as they are (default: moved onto the family's no-contact image, so a "
        "contact keeps its family codes and the family generator's samples decode in the sensor's look)",
    )
    parser.add_argument(
        "--generator-steps", type=positive_int, default=300, help="generator fine-tuning steps (default 300)"
    )
    parser.add_argument("--families", help="a `vqtouch cluster` output of the family tokenizer (default: cluster now)")
    parser.add_argument(
        "--family", type=non_negative_int, help="adapt from this family even when the assignment refuses"
    )
    parser.add_argument(
        "--threshold", type=non_negative_float, help="assignment distance threshold (default: the families' own)"
    )
    parser.add_argument(
        "--samples", type=positive_int, default=32, help="images generated per condition and arm (default 32)"
    )
    parser.add_argument(
        "--eval-images",
        type=positive_int,
        default=64,
        help="held-out images of the new sensor (default 64; never the shots)",
    )
    parser.add_argument(
        "--feature-size",
        type=feature_size_argument,
        default=224,
        help="side EfficientNet-Lite0 sees images at (default 224)",
    )
    add_image_folder_arguments(parser)


@hookimpl
def vqtouch_add_commands(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "fewshot",
        help="from an unseen sensor's images to generated images of it: assign, adapt the tokenizer, "
        "fine-tune the family generator, sample every condition, score",
    )
    _add_fewshot_arguments(parser)
    parser.add_argument(
        "--out", required=True, help="folder for the adapted tokenizer, the generator run and the scores"
    )
    parser.add_argument(
        "--ratio",
        type=family_ratio,
        default=AdaptSettings.ratio,
        help=f"family images per shot, tokenizer and generator alike (default {AdaptSettings.ratio:g}, "
        "vqtouch adapt's; 0: shots alone; 5: the paper's 1:5)",
    )
    parser.add_argument(
        "--seed", type=non_negative_int, default=0, help="draws the shots, the family samples and the samples"
    )
    parser.add_argument("--no-score", action="store_true", help="write the samples without the fd scores")
    parser.add_argument("--overwrite", action="store_true", help="replace what --out holds")
    parser.set_defaults(handler="vqtouch.plugins.experiments.fewshot_generation:_fewshot_command")

    evaluate = command_group(subparsers, "evaluate", "evaluate a trained component")
    table = evaluate.add_parser(
        "fewshot-generation",
        help="vqtouch fewshot over seeds and ratios (0: the shots alone), fd_effnetlite0 per conditioner and arm "
        "as mean ± std (JSON, markdown); resumes a table that was interrupted",
    )
    _add_fewshot_arguments(table)
    add_experiment_arguments(table)
    table.add_argument(
        "--ratios", type=family_ratio, nargs="+", default=[5.0, 0.0], help="family images per shot (default 5 0)"
    )
    table.set_defaults(handler="vqtouch.plugins.experiments.fewshot_table:_evaluate_fewshot_generation_command")

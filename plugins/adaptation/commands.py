"""The cross-sensor commands: ``vqtouch cluster``, ``vqtouch adapt``, ``vqtouch evaluate cross-sensor`` and
``vqtouch evaluate fewshot``.

::

    vqtouch cluster --run TOKRUN --sensors gelsight gelsight_mini digit '{"name": "gelsight", "variant": {...}}' \\
        path/to/real_sensor_frames --out DIR [--images 64] [--features pooled|codes] [--clusterer kmeans]
    vqtouch adapt --run TOKRUN --images DIR_OR_SPEC --shots 50 --ratio 5 --out OUT [--families DIR]
    vqtouch evaluate cross-sensor --run TOKRUN --out DIR
    vqtouch evaluate fewshot --run TOKRUN --out DIR [--target SPEC] [--n 500 2000] [--ratio 5]
    vqtouch evaluate mix-ratio --run TOKRUN --out DIR [--shots 50] [--ratios 0 1 2 5 10] [--steps 200]

``cluster`` writes ``DIR/cluster.json`` (families, members, prototypes, the family distance
matrix, each sensor's distance to every family, and with ``--unseen SPEC ...`` where each unseen
sensor is assigned, or why it is refused), ``DIR/clusterer.safetensors`` and ``DIR/families.png``
(a 2-D PCA embedding of every image's features with the sensors' prototypes); see
:mod:`.families`.  ``adapt`` writes an adapted tokenizer (:mod:`.adapt`); ``evaluate
cross-sensor`` the experiment of :mod:`.evaluation`, ``evaluate fewshot`` that of :mod:`.fewshot`,
``evaluate mix-ratio`` that of :mod:`.ratio`.
"""

from __future__ import annotations

import json

from vqtouch.core import hookimpl
from vqtouch.plugins.cli.app import (
    add_overwrite_argument,
    family_ratio,
    add_image_folder_arguments,
    NumberType,
    add_step_argument,
    command_group,
    learning_rate,
    non_negative_float,
    non_negative_int,
    positive_int,
    seed_int,
)
from vqtouch.plugins.evaluation.records import add_experiment_arguments
from vqtouch.core.image_size import image_size_argument
from vqtouch.plugins.scenes import GELSIGHT_DERIVATIVE_II

from .stages_plugin import AdaptSettings


#: The share of images kept per refinement step, in (0, 1].
_kept_fraction = NumberType(float, 0, 1, low_open=True, what="fraction")


@hookimpl
def vqtouch_add_commands(subparsers):
    """Register ``cluster``, ``adapt`` and the ``evaluate`` experiments of the cross-sensor stages."""
    _add_cluster_command(subparsers)
    _add_adapt_command(subparsers)
    evaluate = command_group(subparsers, "evaluate", "evaluate a trained component")
    _add_cross_sensor_command(evaluate)
    _add_fewshot_command(evaluate)
    _add_mix_ratio_command(evaluate)


def _add_cluster_command(subparsers) -> None:
    """``vqtouch cluster``: fit sensor families from a tokenizer's features."""
    cluster = subparsers.add_parser("cluster", help="group sensors into families from a trained tokenizer's features")
    cluster.add_argument(
        "--run", required=True, help="a run whose tokenizer trained, a checkpoint folder or a bundle (pretrained:NAME)"
    )
    add_step_argument(cluster)
    cluster.add_argument(
        "--sensors",
        nargs="+",
        required=True,
        metavar="SPEC",
        help="sensors: registered family names, JSON with a variant, or folders of images",
    )
    cluster.add_argument("--out", required=True, help="folder for cluster.json and families.png")
    add_overwrite_argument(cluster, "cluster.json")
    cluster.add_argument("--images", type=positive_int, default=64, help="images per sensor (default 64)")
    cluster.add_argument(
        "--image-size", type=image_size_argument, help="image size, S or HEIGHTxWIDTH (default: the tokenizer's)"
    )
    cluster.add_argument(
        "--features",
        choices=("pooled", "codes"),
        default="pooled",
        help="pooled encoder features or code histograms (default pooled)",
    )
    cluster.add_argument("--clusterer", default="kmeans", help="clusterer plugin (default kmeans)")
    cluster.add_argument(
        "--families", type=non_negative_int, default=0, help="number of families (0: chosen by silhouette)"
    )
    cluster.add_argument(
        "--refine-steps", type=non_negative_int, default=3, help="prototype refinement steps (default 3)"
    )
    cluster.add_argument("--keep", type=_kept_fraction, default=0.8, help="fraction of images kept per refinement step")
    cluster.add_argument("--seed", type=seed_int, default=0, help="seed of the rendered scenes")
    cluster.add_argument(
        "--unseen",
        nargs="+",
        default=[],
        metavar="SPEC",
        help="sensors to assign to the fitted families without joining them (zero-shot)",
    )
    cluster.add_argument(
        "--threshold",
        type=non_negative_float,
        help="refuse an unseen sensor farther than this from every family (default: 3x the "
        "largest within-family spread, at least half the nearest two families' distance)",
    )
    add_image_folder_arguments(cluster)
    cluster.set_defaults(handler="vqtouch.plugins.adaptation.command_handlers:cmd_cluster")


def _add_adapt_command(subparsers) -> None:
    """``vqtouch adapt``: fine-tune a family tokenizer on an unseen sensor's shots."""
    adapt = subparsers.add_parser("adapt", help="adapt a family tokenizer to an unseen sensor from a few of its images")
    adapt.add_argument(
        "--run",
        required=True,
        help="the family tokenizer: a run whose tokenizer trained, a checkpoint folder or a bundle (pretrained:NAME)",
    )
    add_step_argument(adapt)
    adapt.add_argument(
        "--images",
        required=True,
        metavar="DIR_OR_SPEC",
        help="the unseen sensor: a folder of its images, or a registered sensor (name or JSON variant)",
    )
    adapt.add_argument("--out", required=True, help="folder for the adapted tokenizer, adapt.json and before_after.png")
    adapt.add_argument("--shots", type=positive_int, default=50, help="unseen-sensor images to train on (default 50)")
    adapt.add_argument(
        "--ratio",
        type=family_ratio,
        default=AdaptSettings.ratio,
        help=f"family images per shot in the mixed set (default {AdaptSettings.ratio:g}, measured with `vqtouch "
        "evaluate mix-ratio`; the paper's 1:5 needs about 6x the shots-alone steps to see the sensor as often)",
    )
    adapt.add_argument(
        "--steps",
        type=positive_int,
        default=AdaptSettings.steps,
        help=f"fine-tuning steps (default {AdaptSettings.steps})",
    )
    adapt.add_argument(
        "--part",
        choices=("all", "decoder"),
        default="all",
        help="what fine-tunes: all (default), or the decoder alone: the encoder and codebook stay, so every "
        "image keeps its codes and a generator trained over them still fits",
    )
    adapt.add_argument("--learning-rate", type=learning_rate, help="default: the run's tokenizer.train.learning_rate")
    adapt.add_argument("--batch-size", type=positive_int, help="default: the run's data.batch_size")
    adapt.add_argument(
        "--eval-images",
        type=positive_int,
        default=64,
        help="held-out unseen-sensor images scored before and after (default 64)",
    )
    adapt.add_argument(
        "--families",
        help="a `vqtouch cluster` output folder (default: cluster the registered "
        "sensor families and 3 variants of each, written with the sensor's "
        "assignment to OUT/families)",
    )
    adapt.add_argument(
        "--threshold",
        type=non_negative_float,
        help="refuse a sensor farther than this from every family (default: the clustering's refusal threshold)",
    )
    adapt.add_argument("--family", type=non_negative_int, help="adapt from this family, whatever the assignment says")
    adapt.add_argument("--seed", type=seed_int, default=0, help="seed of the shots' draw and the rendered scenes")
    adapt.add_argument("--overwrite", action="store_true", help="replace an adapted tokenizer already in --out")
    add_image_folder_arguments(adapt)
    adapt.set_defaults(handler="vqtouch.plugins.adaptation.command_handlers:cmd_adapt")


def _add_cross_sensor_command(evaluate) -> None:
    """``vqtouch evaluate cross-sensor``: the cross-sensor experiment."""
    cross = evaluate.add_parser(
        "cross-sensor",
        help="family recovery, few-shot transfer arms, real frames and cost "
        "of adapting a family tokenizer (JSON, markdown, PNG)",
    )
    cross.add_argument("--run", required=True, help="the family tokenizer's run")
    cross.add_argument("--out", required=True, help="folder for cross_sensor.json/.md/.png and the arms' tokenizers")
    add_overwrite_argument(cross, "cross_sensor.json")
    cross.add_argument(
        "--target",
        default=json.dumps(GELSIGHT_DERIVATIVE_II),
        help="the unseen sensor (default: the zero-shot scene's damaged, drifted GelSight)",
    )
    cross.add_argument("--seeds", type=seed_int, nargs="+", default=[0, 1, 2], help="seeds (default 0 1 2)")
    cross.add_argument("--steps", type=positive_int, default=200, help="fine-tuning steps of every arm (default 200)")
    cross.add_argument(
        "--shots",
        type=positive_int,
        nargs="+",
        default=[10, 25, 50, 100],
        help="shot counts of arms b and c (default 10 25 50 100)",
    )
    cross.add_argument("--main-shots", type=positive_int, default=50, help="shots of the ratio sweep (default 50)")
    cross.add_argument(
        "--ratios",
        type=family_ratio,
        nargs="+",
        default=[1.0, 5.0, 20.0],
        help="family images per shot in arm c (default 1 5 20)",
    )
    cross.add_argument("--main-ratio", type=non_negative_float, default=5.0, help="ratio of the shots sweep (5)")
    cross.add_argument(
        "--everything",
        type=non_negative_int,
        default=1000,
        help="target images of arm d, mixed 1:1 with family data (0 skips arm d and the cost)",
    )
    cross.add_argument("--eval-images", type=positive_int, default=64, help="held-out target images (default 64)")
    cross.add_argument("--variants", type=positive_int, default=4, help="variants per family to cluster (default 4)")
    cross.add_argument(
        "--held-out-variants", type=positive_int, default=2, help="further variants per family to assign (default 2)"
    )
    cross.add_argument("--images", type=positive_int, default=32, help="images per sensor for clustering (default 32)")
    cross.add_argument("--clusterers", nargs="+", default=["kmeans", "agglomerative"], help="clusterer plugins")
    cross.add_argument(
        "--real",
        default="gelsight_mini",
        help="a sensor family whose captured frames play the unseen sensor ('none' skips)",
    )
    cross.add_argument(
        "--real-shots",
        type=positive_int,
        nargs="+",
        default=[4, 8, 16],
        help="shots from the real frames (default 4 8 16; the rest are held out)",
    )
    add_image_folder_arguments(cross)
    cross.set_defaults(handler="vqtouch.plugins.adaptation.command_handlers:cmd_evaluate_cross_sensor")


def _add_fewshot_command(evaluate) -> None:
    """``vqtouch evaluate fewshot``: the few-shot reconstruction experiment."""
    fewshot = evaluate.add_parser(
        "fewshot",
        help="few-shot reconstruction of an unseen sensor from N of its images "
        "(Table 4): from scratch, zero-shot, fine-tuned on the N alone, "
        "mixed 1:ratio with family data (JSON, markdown, PNG)",
    )
    fewshot.add_argument("--run", required=True, help="the family tokenizer's run (its config trains the scratch arm)")
    add_experiment_arguments(fewshot)
    fewshot.add_argument(
        "--target",
        default=json.dumps(GELSIGHT_DERIVATIVE_II),
        help="the unseen sensor: a registered sensor (name or JSON variant) or a folder of its "
        "images (default: the zero-shot scene's damaged, drifted GelSight)",
    )
    fewshot.add_argument(
        "--n",
        type=positive_int,
        nargs="+",
        default=[500, 2000],
        metavar="N",
        help="unseen-sensor images each arm learns from (default 500 2000)",
    )
    fewshot.add_argument(
        "--ratio",
        type=family_ratio,
        default=5.0,
        help="family images per target image in the mixed arm (default 5: the paper's 1:5)",
    )
    fewshot.add_argument(
        "--steps",
        type=positive_int,
        default=200,
        help="fine-tuning steps of the shots-alone and mixed arms (default 200)",
    )
    fewshot.add_argument(
        "--scratch-steps",
        type=positive_int,
        help="training steps of the scratch arm (default: the run's tokenizer.train.steps)",
    )
    fewshot.add_argument(
        "--eval-images",
        type=positive_int,
        default=64,
        help="held-out unseen-sensor images every arm is scored on (default 64)",
    )
    fewshot.add_argument(
        "--families",
        help="a `vqtouch cluster` output of this tokenizer (default: cluster the "
        "registered sensor families and 3 variants of each into OUT/families)",
    )
    add_image_folder_arguments(fewshot)
    fewshot.set_defaults(handler="vqtouch.plugins.adaptation.command_handlers:cmd_evaluate_fewshot")


def _add_mix_ratio_command(evaluate) -> None:
    """``vqtouch evaluate mix-ratio``: the family-to-shot mix ratio sweep."""
    ratio = evaluate.add_parser(
        "mix-ratio",
        help="how many family images to mix with each shot of an unseen sensor: ratios at equal "
        "steps and at equal sensor exposures, against the shots alone and all the sensor's images "
        "(JSON, markdown, PNG)",
    )
    ratio.add_argument("--run", required=True, help="the family tokenizer's run")
    add_experiment_arguments(ratio)
    ratio.add_argument(
        "--target",
        default=json.dumps(GELSIGHT_DERIVATIVE_II),
        help="the unseen sensor: a registered sensor (name or JSON variant) or a folder of its "
        "images (default: the zero-shot scene's damaged, drifted GelSight)",
    )
    ratio.add_argument("--shots", type=positive_int, default=50, help="unseen-sensor images to adapt on (default 50)")
    ratio.add_argument(
        "--ratios",
        type=family_ratio,
        nargs="+",
        default=[0.0, 1.0, 2.0, 5.0, 10.0],
        help="family images per shot (default 0 1 2 5 10; 0 is the shots alone)",
    )
    ratio.add_argument(
        "--steps",
        type=positive_int,
        default=200,
        help="fine-tuning steps at equal steps; the equal-exposure arms train steps x (1 + ratio) (default 200)",
    )
    ratio.add_argument(
        "--all-images",
        type=positive_int,
        default=1000,
        help="the sensor's images the all-images reference trains on (default 1000; a folder: all not held out)",
    )
    ratio.add_argument(
        "--eval-images",
        type=positive_int,
        default=64,
        help="held-out unseen-sensor images every arm is scored on (default 64)",
    )
    ratio.add_argument(
        "--families",
        help="a `vqtouch cluster` output of this tokenizer (default: cluster the "
        "registered sensor families and 3 variants of each into OUT/families)",
    )
    ratio.add_argument(
        "--cost-controls",
        type=non_negative_float,
        nargs="+",
        default=[],
        metavar="RATIO",
        help="mix ratios whose equal-exposure step count the shots alone also train for, telling the longer "
        "training from the mix (default none)",
    )
    add_image_folder_arguments(ratio)
    ratio.set_defaults(handler="vqtouch.plugins.adaptation.command_handlers:cmd_evaluate_mix_ratio")

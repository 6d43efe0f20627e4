"""The ``cluster`` and ``adapt`` stages' plugin: their sections, the adaptation settings and their registration
(the stages, in stages.py, are imported when they run)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from pydantic import Field

from vqtouch.core import Section, Slot, hookimpl


@dataclass
class AdaptSettings:
    """How to adapt (the ``vqtouch adapt`` options and the ``adapt`` stage's section)."""

    shots: int = 50
    #: Family images per shot.  1:1 for 400 steps sees the sensor's images as often as the shots alone
    #: do in 200, keeps the family (its held-out PSNR 33.9 dB against 25.3 for the shots alone) and is
    #: level with the shots alone on the sensor; the paper's 1:5 at 200 steps was 0.032 SSIM behind
    #: (``vqtouch evaluate mix-ratio``, docs/results.md "How many family images per shot").
    ratio: float = 1.0
    steps: int = 400
    learning_rate: float | None = None
    batch_size: int | None = None
    eval_images: int = 64
    threshold: float | None = None
    family: int | None = None
    seed: int = 0
    #: What fine-tunes: ``"all"`` (encoder, codebook and decoder) or ``"decoder"`` (the encoder and the
    #: codebook stay, so every image keeps its codes and a generator over them stays valid; the
    #: decoder learns to draw the new sensor from them).
    part: str = "all"
    #: Re-base the sensor's images onto the family's no-contact image before encoding (and back after
    #: decoding; :attr:`vqtouch.plugins.tokenizer.Tokenizer.rebase_3HW`): a contact keeps the codes it
    #: has on the family's sensor, which is what a family generator draws, however far the sensor's
    #: look is from the family's.  ``vqtouch fewshot`` turns it on.
    rebase: bool = False
    #: Metric plugins scoring the held-out images before and after (``fd_effnetlite0`` adds a
    #: distribution score; it needs at least 2 held-out images).
    metrics: tuple[str, ...] = ("ssim", "psnr")


class ClusterSection(Section):
    """The ``cluster`` stage's section."""

    clusterer: Slot("clusterer") | None = Field(
        None, description="Clustering plugin that groups sensors into families from tokenizer features."
    )
    sensors: list[str] | None = Field(
        None,
        description="Sensors to group: registered family names, JSON sensor configs with a variant, or "
        "folders of a real sensor's images; null: every registered family plus "
        "`variants_per_family` random environmental variants of each.",
    )
    variants_per_family: int = Field(
        3, ge=0, le=50, description="Random environmental variants per registered family when `sensors` is null."
    )
    images_per_sensor: int = Field(32, ge=1, le=10_000, description="Images of each sensor that make its prototype.")
    features: Literal["pooled", "codes"] = Field("pooled", description="Pooled encoder features or code histograms.")
    refine_steps: int = Field(
        3, ge=0, le=100, description="Prototype refinement steps (drop the farthest images, re-average)."
    )
    keep: float = Field(0.8, gt=0.0, le=1.0, description="Fraction of images kept at each refinement step.")
    threshold: float | None = Field(
        None,
        ge=0.0,
        description="Refuse an unseen sensor farther than this from every "
        "family; null: derived from the within-family spread.",
    )
    family_tokenizer: str | None = Field(
        None,
        description="The tokenizer the families are fitted with (and adapted from): null, this run's own "
        "tokenizer stage; a tokenizer run or checkpoint folder; or pretrained:NAME, a bundled one "
        "(the tour demo's: a tokenizer trained for demo minutes has features too weak to show "
        "families).  The cluster and adapt stages of one run must name the same.",
    )


class AdaptSection(Section):
    """The ``adapt`` stage's section: how the family tokenizer is adapted to the target sensor."""

    shots: int = Field(50, ge=1, le=100_000, description="Target-sensor images to train on.")
    ratio: float = Field(
        AdaptSettings.ratio,
        ge=0.0,
        le=1000.0,
        description="Family images per shot in the mixed set (measured by `vqtouch evaluate mix-ratio`; "
        "the paper's 1:5 is 5).",
    )
    steps: int = Field(AdaptSettings.steps, ge=1, le=1_000_000, description="Fine-tuning steps.")
    learning_rate: float | None = Field(
        None, gt=0.0, le=10.0, description="Fine-tuning learning rate; null: the tokenizer's own."
    )
    eval_images: int = Field(64, ge=1, le=100_000, description="Held-out target images scored before and after.")
    threshold: float | None = Field(
        None,
        ge=0.0,
        description="Refuse a target farther than this from every family; null: the clustering's threshold.",
    )
    family_tokenizer: str | None = Field(
        None,
        description="The tokenizer the families are fitted with (and adapted from): null, this run's own "
        "tokenizer stage; a tokenizer run or checkpoint folder; or pretrained:NAME, a bundled one "
        "(the tour demo's: a tokenizer trained for demo minutes has features too weak to show "
        "families).  The cluster and adapt stages of one run must name the same.",
    )
    family: int | None = Field(None, ge=0, description="Adapt from this family whatever the assignment says.")
    rebase: bool = Field(
        AdaptSettings.rebase,
        description="Re-base the target's images onto the family's no-contact image (the per-pixel median of the "
        "family images drawn) before encoding and back after decoding; the fewshot stage reuses this stage's "
        "tokenizer only when it was adapted as its own `rebase` asks.",
    )


@hookimpl
def vqtouch_register_stages(register):
    register(
        "cluster",
        "vqtouch.plugins.adaptation.stages:run_cluster_stage",
        section=ClusterSection,
        needs=("tokenizer.autoencoder", "tokenizer.quantizer", "cluster.clusterer"),
        uses=("metrics",),
        makes=("families",),
        demo={"images_per_sensor": 16, "variants_per_family": 2},
        description="Cluster sensors into families from tokenizer features; assign an unseen sensor to one.",
    )
    register(
        "adapt",
        "vqtouch.plugins.adaptation.stages:run_adapt_stage",
        section=AdaptSection,
        needs=("tokenizer.autoencoder", "tokenizer.quantizer", "sensor", "target_sensor"),
        makes=("adapted_tokenizer",),
        demo={"steps": 30, "shots": 20, "eval_images": 16},
        trains="steps",
        description="Adapt the family tokenizer to the target sensor from a few of its images mixed 1:5 with "
        "family data.",
    )

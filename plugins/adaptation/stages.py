"""The ``cluster`` and ``adapt`` stages' sections and slots.

``cluster`` groups sensors into families from tokenizer features (its ``cluster.clusterer``
slot) and assigns an unseen sensor to one; ``adapt`` fine-tunes the family tokenizer with a
few images of the experiment's ``target_sensor`` mixed with family data.  Both are declared
so scenes and configs that use them validate; running them is not implemented in this
version, and each stage says so when asked to run.
"""

from __future__ import annotations

from typing import Any

from pydantic import Field

from vqtouch.core import Section, Slot, StageJob, StageUnavailable, hookimpl


class ClusterSection(Section):
    """The ``cluster`` stage's section."""

    clusterer: Slot("clusterer") | None = Field(None, description="Clustering plugin that groups sensors into "
                                                                  "families from tokenizer features.")


def run_cluster_stage(job: StageJob) -> dict[str, Any]:
    """Not implemented in this version: says so (after the slots were checked)."""
    raise StageUnavailable("sensor-family clustering is not implemented in this version of vqtouch")


def run_adapt_stage(job: StageJob) -> dict[str, Any]:
    """Not implemented in this version: says so (after the slots were checked)."""
    raise StageUnavailable("few-shot adaptation to the target sensor is not implemented in this version of vqtouch")


@hookimpl
def vqtouch_register_stages(register):
    register("cluster", run_cluster_stage, section=ClusterSection,
             needs=("data.dataset", "tokenizer.autoencoder", "tokenizer.quantizer", "cluster.clusterer"),
             description="Cluster sensors into families from tokenizer features; assign an unseen sensor to one.")
    register("adapt", run_adapt_stage,
             needs=("data.dataset", "tokenizer.autoencoder", "tokenizer.quantizer", "sensor", "target_sensor"),
             description="Adapt the family tokenizer to the target sensor from a few of its images mixed 1:5 with "
                         "family data.")

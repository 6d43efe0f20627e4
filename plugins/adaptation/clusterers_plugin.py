"""The ``kmeans`` and ``agglomerative`` clusterers' plugin: their options and registration (the clusterers,
in clusterers.py, are imported when built)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from vqtouch.core import PluginConfig, hookimpl


class FamilyClustererOptions(PluginConfig):
    """Options shared by the family clusterers; subclasses narrow ``name``."""

    num_families: int = Field(
        0,
        ge=0,
        le=1000,
        description="Number of sensor families; 0 chooses it in [2, max_families] by the best silhouette score.",
    )
    max_families: int = Field(8, ge=2, le=1000, description="Largest family count tried when num_families is 0.")
    seed: int = Field(0, ge=0, le=2**31 - 1, description="Seed of the clustering's random starts (k-means).")


class KMeansConfig(FamilyClustererOptions):
    """Options of the ``kmeans`` clusterer."""

    name: Literal["kmeans"] = "kmeans"
    restarts: int = Field(10, ge=1, le=1000, description="k-means runs from different starts; the best is kept.")


class AgglomerativeConfig(FamilyClustererOptions):
    """Options of the ``agglomerative`` clusterer."""

    name: Literal["agglomerative"] = "agglomerative"


@hookimpl
def vqtouch_register_clusterers(register):
    register(
        "kmeans",
        "vqtouch.plugins.adaptation.clusterers:build_kmeans",
        KMeansConfig,
        description="Sensor families by k-means over sensor prototypes (count given or by silhouette); "
        "an unseen sensor joins the nearest family mean.",
    )
    register(
        "agglomerative",
        "vqtouch.plugins.adaptation.clusterers:build_agglomerative",
        AgglomerativeConfig,
        description="Sensor families by Ward agglomerative clustering (deterministic); an unseen sensor joins "
        "the nearest family mean.",
    )

"""Sensor-family clusterers over scikit-learn: ``kmeans`` and ``agglomerative``.

Both group feature rows (one per sensor: its prototype, the mean tokenizer feature of its images)
into families and keep one centroid per family, the mean of its members' rows.  A new row (an
unseen sensor) is assigned to the family whose centroid is nearest, the paper's
D(C_i, C_j) = ||mean(C_i) - mean(C_j)||.  The centroids are a buffer, so a fitted clusterer is
saved and restored with its checkpoint (its size is set by the file).

- ``kmeans``: k-means with ``num_families`` families, or, with ``num_families=0``, the count in
  [2, ``max_families``] with the best silhouette score.
- ``agglomerative``: Ward-linkage agglomerative clustering, the same family count rule; it needs
  no random start, so tiny sets of sensors cluster the same way on every machine.

scikit-learn runs in float64 on the CPU; features arrive as any float tensor.
"""

from __future__ import annotations

from typing import Any

import torch

from vqtouch.core import BuildContext, Clusterer, ConfigError
from vqtouch.plugins.utils.threads import on_one_thread

from .clusterers_plugin import AgglomerativeConfig, FamilyClustererOptions, KMeansConfig


class FamilyClusterer(Clusterer):
    """Fits families with a scikit-learn clustering (``_labels``) and predicts by nearest family mean."""

    def __init__(self, options: FamilyClustererOptions) -> None:
        super().__init__()
        self.options = options
        self.register_buffer("centroids_KF", torch.zeros(0, 0, dtype=torch.float64))
        #: How the last fit chose its family count: ``given``, or the silhouette of each count it
        #: scored and how many distinct rows there were (:func:`family_count_note` reads it).
        self.count_choice: dict[str, Any] = {}

    @property
    def num_families(self) -> int:
        """Families found by the last fit (0 before any)."""
        return int(self.centroids_KF.shape[0])

    def _labels(self, features_NF: Any, count: int) -> Any:
        """scikit-learn labels (N,) of float64 numpy features for ``count`` families."""
        raise NotImplementedError

    def _check(self, features_NF: torch.Tensor) -> torch.Tensor:
        if features_NF.ndim != 2 or features_NF.shape[0] == 0:
            raise ValueError(f"expected features (N, F) with N >= 1, got {tuple(features_NF.shape)}")
        features = features_NF.detach().to("cpu", torch.float64)
        if not torch.isfinite(features).all():
            raise ValueError("features contain NaN or Inf")
        return features

    @on_one_thread  # k-means, silhouette and the means: the same families whatever the thread count
    def fit(self, features_NF: torch.Tensor) -> torch.Tensor:
        """Group the (N, F) rows into families; returns each row's family (N,), numbered by first
        appearance (row 0 is in family 0), and keeps the family means for :meth:`predict`."""
        features = self._check(features_NF)
        rows = features.shape[0]
        distinct = int(torch.unique(features, dim=0).shape[0])
        if self.options.num_families:
            if self.options.num_families > distinct:
                raise ConfigError(
                    f"{self.options.num_families} families asked of {distinct} distinct sensor "
                    f"feature(s); set num_families <= {distinct}, or 0 to choose by silhouette"
                )
            labels = self._labels(features.numpy(), self.options.num_families)
            self.count_choice = {"chosen_by": "given"}
        else:
            largest = min(self.options.max_families, distinct - 1)
            labels, silhouettes = self._best_by_silhouette(features.numpy(), largest)
            self.count_choice = {
                "chosen_by": "silhouette",
                "silhouette": silhouettes,
                "distinct_rows": distinct,
                "max_families": self.options.max_families,
            }
        labels_N = _first_appearance_order(torch.as_tensor(labels, dtype=torch.long))
        count = int(labels_N.max()) + 1 if rows else 0
        centroids = torch.stack([features[labels_N == family].mean(dim=0) for family in range(count)])
        self.centroids_KF = centroids.to(self.centroids_KF.device)
        return labels_N

    def _best_by_silhouette(self, features: Any, largest: int) -> tuple[Any, dict[int, float]]:
        """Labels with the best silhouette over 2..``largest`` families (one family when fewer than
        three distinct rows leave nothing to compare), and the silhouette of each count scored."""
        import numpy as np
        from sklearn.metrics import silhouette_score

        silhouettes: dict[int, float] = {}
        if largest < 2:
            return np.zeros(len(features), dtype=np.int64), silhouettes
        best, best_score = None, -np.inf
        for count in range(2, largest + 1):
            labels = self._labels(features, count)
            if len(set(labels.tolist())) < 2:
                continue
            score = silhouette_score(features, labels)
            silhouettes[count] = round(float(score), 4)
            if score > best_score + 1e-12:  # ties keep the fewer families
                best, best_score = labels, score
        return (best if best is not None else np.zeros(len(features), dtype=np.int64)), silhouettes

    @on_one_thread
    def distances(self, features_NF: torch.Tensor) -> torch.Tensor:
        """Euclidean distances (N, K) from each row to each family mean (float64)."""
        if self.num_families == 0:
            raise RuntimeError("the clusterer is not fitted: call fit() first (or load a fitted checkpoint)")
        features = self._check(features_NF)
        if features.shape[1] != self.centroids_KF.shape[1]:
            raise ValueError(
                f"features have {features.shape[1]} dimensions; the families were fitted on "
                f"{self.centroids_KF.shape[1]}"
            )
        return torch.cdist(features, self.centroids_KF.cpu())

    def predict(self, features_NF: torch.Tensor) -> torch.Tensor:
        """The nearest family (N,) of each row (ties go to the lower family index)."""
        return self.distances(features_NF).argmin(dim=1)

    def resize_to_state(self, tensors: dict[str, torch.Tensor]) -> None:
        """Take the number of families (and feature width) of a saved state before it is loaded:
        it is learned by :meth:`fit`, not set by the config (see ``core.checkpoint.load_state_strict``)."""
        saved = tensors.get("centroids_KF")
        if saved is not None and saved.ndim == 2:
            self.centroids_KF = torch.zeros(saved.shape, dtype=self.centroids_KF.dtype, device=self.centroids_KF.device)

    def extra_repr(self) -> str:
        return f"families={self.num_families}"


def _first_appearance_order(labels_N: torch.Tensor) -> torch.Tensor:
    """Renumber labels 0, 1, ... in order of first appearance (so equal partitions get equal labels)."""
    mapping: dict[int, int] = {}
    return torch.tensor([mapping.setdefault(int(label), len(mapping)) for label in labels_N], dtype=torch.long)


class KMeansClusterer(FamilyClusterer):
    """Sensor families by k-means (scikit-learn ``KMeans``, k-means++ starts)."""

    def _labels(self, features: Any, count: int) -> Any:
        from sklearn.cluster import KMeans

        return KMeans(n_clusters=count, n_init=self.options.restarts, random_state=self.options.seed).fit_predict(
            features
        )


class AgglomerativeClusterer(FamilyClusterer):
    """Sensor families by Ward-linkage agglomerative clustering (scikit-learn), deterministic."""

    def _labels(self, features: Any, count: int) -> Any:
        from sklearn.cluster import AgglomerativeClustering

        return AgglomerativeClustering(n_clusters=count, linkage="ward").fit_predict(features)


def build_kmeans(config: KMeansConfig, context: BuildContext) -> KMeansClusterer:
    """Factory for ``kmeans``."""
    return KMeansClusterer(config)


def build_agglomerative(config: AgglomerativeConfig, context: BuildContext) -> AgglomerativeClusterer:
    """Factory for ``agglomerative``."""
    return AgglomerativeClusterer(config)

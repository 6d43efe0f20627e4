"""Sensor families from tokenizer features: what ``vqtouch cluster`` computes.

Each sensor contributes images: a registered sensor family (with or without a variant) renders
the embedded procedural scenes, a folder holds a real sensor's images.  The trained tokenizer's
encoder turns every image into a feature vector:

- ``pooled``: the encoder's latent map averaged over positions, then its per-channel spread
  (mean and standard deviation over positions: 2 x latent channels);
- ``codes``: the normalised histogram of the image's codes (codebook-size entries).

A sensor's prototype is the mean feature of its images, refined iteratively: the images
farthest from the current prototype (the ``1 - keep`` fraction, e.g. stray no-contact or
damaged frames) are dropped and the mean recomputed, ``refine_steps`` times.  A clusterer plugin
then groups the prototypes into families; the distance between families is
D(C_i, C_j) = ||mean(C_i) - mean(C_j)|| over their members' prototypes.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import torch

from vqtouch.core import ConfigError, DatasetError

FeatureKind = Literal["pooled", "codes"]


@torch.no_grad()
def image_features(tokenizer: Any, images_B3HW: torch.Tensor, kind: FeatureKind = "pooled",
                   batch_size: int = 32) -> torch.Tensor:
    """Tokenizer features (B, F) of images in [0, 1] (float64; see the module docstring)."""
    if kind not in ("pooled", "codes"):
        raise ValueError(f"feature kind {kind!r}: expected 'pooled' or 'codes'")
    rows = []
    for chunk in images_B3HW.split(batch_size):
        if kind == "pooled":
            latents = tokenizer.autoencoder.encode(chunk * 2 - 1).double().flatten(2)
            rows.append(torch.cat([latents.mean(dim=2), latents.std(dim=2, correction=0)], dim=1))
        else:
            codes = tokenizer.encode_codes(chunk).flatten(1)
            size = tokenizer.quantizer.codebook_size
            counts = torch.zeros(len(codes), size, dtype=torch.float64)
            counts.scatter_add_(1, codes.long().cpu(), torch.ones_like(codes, dtype=torch.float64).cpu())
            rows.append(counts / codes.shape[1])
    return torch.cat(rows).cpu()


def sensor_prototype(features_NF: torch.Tensor, refine_steps: int = 3, keep: float = 0.8) -> torch.Tensor:
    """The prototype (F,) of one sensor's image features: the mean, refined ``refine_steps`` times
    by keeping the ``keep`` fraction of images nearest to it (at least one)."""
    if features_NF.ndim != 2 or len(features_NF) == 0:
        raise ValueError(f"a prototype needs features (N, F) with N >= 1, got {tuple(features_NF.shape)}")
    if not 0 < keep <= 1:
        raise ValueError(f"keep must lie in (0, 1], got {keep}")
    features = features_NF.double()
    prototype = features.mean(dim=0)
    kept = max(1, round(keep * len(features)))
    for _ in range(refine_steps):
        nearest = (features - prototype).norm(dim=1).argsort(stable=True)[:kept]
        prototype = features[nearest].mean(dim=0)
    return prototype


@dataclass
class SensorImages:
    """One sensor's images for clustering: a display name, where they came from and (N, 3, S, S)."""

    name: str
    source: str
    images: torch.Tensor


def sensor_images(spec: str, host: Any, *, count: int, image_size: int, seed: int = 0) -> SensorImages:
    """The images of ``spec``: a folder of image files (the first ``count``, natural order), or a
    registered sensor family given by name or JSON (``{"name": "gelsight", "variant": {...}}``),
    which renders ``count`` procedural scenes."""
    from vqtouch.core import BuildContext
    from vqtouch.core.images import ImageLoader
    from vqtouch.plugins.data.readers._io import list_images

    path = Path(spec).expanduser()
    if path.is_dir():
        files = list_images(path)
        if not files:
            raise DatasetError(f"{path}: no image files (png, jpg, ...) in this folder")
        loader = ImageLoader(size=image_size)
        images = []
        for file in files[:count]:
            images.append(loader.load(file))  # DatasetError names the file that does not decode
        return SensorImages(path.name, str(path), torch.stack(images))
    text = spec.strip()
    try:
        config = json.loads(text) if text.startswith("{") else {"name": text}
    except json.JSONDecodeError as exc:
        raise ConfigError(f"sensor {spec!r}: not a folder, a sensor name or valid JSON ({exc})") from None
    if not isinstance(config, dict) or "name" not in config:
        raise ConfigError(f"sensor {spec!r}: a JSON sensor needs a 'name', e.g. {{\"name\": \"gelsight\"}}")
    if config["name"] not in host.registry("sensor_family").names():
        raise ConfigError(f"sensor {spec!r} is neither a folder nor a registered sensor family "
                          f"({', '.join(host.registry('sensor_family').names())})")
    sensor = host.build("sensor_family", config)
    dataset = host.build("dataset", {"name": "procedural", "num_samples": count, "image_size": image_size,
                                     "seed": seed}, BuildContext(image_size=image_size), sensor=sensor)
    images = dataset.render_batch(list(range(count)))["tactile"]
    label = config["name"] + ("" if set(config) == {"name"} else "*")
    return SensorImages(label, json.dumps(config, sort_keys=True), images)


def cluster_prototypes(names: list[str], prototypes_SF: torch.Tensor, clusterer: Any) -> dict[str, Any]:
    """Families of the sensors' prototypes (``clusterer`` is fitted here): each sensor's family, the
    members of each family, the family distance matrix D(C_i, C_j) = ||mean(C_i) - mean(C_j)||,
    every sensor's distance to every family mean, each family's spread and the distance beyond
    which an unseen sensor is refused (:func:`refusal_threshold`)."""
    labels = clusterer.fit(prototypes_SF)
    centroids = clusterer.centroids_KF.double().cpu()
    distances = torch.cdist(centroids, centroids)
    to_families = clusterer.distances(prototypes_SF)
    spreads = within_family_spread(prototypes_SF, labels, centroids)
    return {
        "within_family_spread": [round(value, 6) for value in spreads],
        "refusal_threshold": round(refusal_threshold(spreads, centroids), 6),
        "families": [[names[i] for i in range(len(names)) if int(labels[i]) == family]
                     for family in range(clusterer.num_families)],
        "sensor_family": {name: int(label) for name, label in zip(names, labels)},
        "family_distances": [[round(float(value), 6) for value in row] for row in distances],
        "sensor_to_family_distances": {name: [round(float(v), 6) for v in row] for name, row in zip(names, to_families)},
    }


#: An unseen sensor farther from every family mean than this many times the largest within-family
#: spread is refused (see :func:`assign_to_family`).
REFUSAL_FACTOR = 3.0


def within_family_spread(prototypes_SF: torch.Tensor, labels_S: torch.Tensor, centroids_KF: torch.Tensor) -> list[float]:
    """Each family's spread: the largest distance of a member's prototype to the family mean."""
    distances = (prototypes_SF.double() - centroids_KF.double()[labels_S]).norm(dim=1)
    return [float(distances[labels_S == family].max()) for family in range(len(centroids_KF))]


def refusal_threshold(spreads: list[float], centroids_KF: torch.Tensor, factor: float = REFUSAL_FACTOR) -> float:
    """The distance beyond which an unseen sensor matches no family: ``factor`` times the largest
    within-family spread, and never less than half the distance between the two nearest families
    (a family of a few sensors has too little spread to go by; a sensor within half that distance
    of a family is nearer to it than any two families are to each other)."""
    floor = 0.0
    if len(centroids_KF) > 1:
        between = torch.cdist(centroids_KF.double(), centroids_KF.double())
        floor = float(between[~torch.eye(len(centroids_KF), dtype=torch.bool)].min()) / 2
    return max(factor * max(spreads, default=0.0), floor)


def assign_to_family(clusterer: Any, prototype_F: torch.Tensor, threshold: float) -> dict[str, Any]:
    """Where an unseen sensor's prototype belongs: its distance to every family mean, the nearest
    family, the margin to the second nearest, and ``refused`` when even the nearest is farther than
    ``threshold`` (then ``family`` is None: no silent wrong assignment)."""
    distances = clusterer.distances(prototype_F.unsqueeze(0))[0]
    order = distances.argsort(stable=True)
    nearest = int(order[0])
    margin = float(distances[order[1]] - distances[nearest]) if len(order) > 1 else float("inf")
    refused = float(distances[nearest]) > threshold
    return {"family": None if refused else nearest, "nearest_family": nearest, "refused": refused,
            "distances": [round(float(v), 6) for v in distances], "margin": round(margin, 6),
            "threshold": round(threshold, 6)}


def plot_families(names: list[str], features_by_sensor: list[torch.Tensor], prototypes_SF: torch.Tensor,
                  labels: list[int], path: Path, title: str) -> None:
    """A 2-D PCA embedding (fitted on every image feature) of the images (small points) and the
    prototypes (large markers, coloured by family, labelled by sensor)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from sklearn.decomposition import PCA

    everything = torch.cat(features_by_sensor).numpy()
    pca = PCA(n_components=min(2, everything.shape[1], len(everything)), random_state=0).fit(everything)
    figure = Figure(figsize=(7, 6), dpi=110)
    FigureCanvasAgg(figure)
    axes = figure.add_subplot(1, 1, 1)
    colours = [f"C{label % 10}" for label in labels]
    for features, colour in zip(features_by_sensor, colours):
        points = pca.transform(features.numpy())
        axes.scatter(points[:, 0], points[:, 1] if points.shape[1] > 1 else 0 * points[:, 0], s=6, alpha=0.3,
                     color=colour)
    centres = pca.transform(prototypes_SF.numpy())
    for (x, *rest), name, colour, label in zip(centres, names, colours, labels):
        y = rest[0] if rest else 0.0
        axes.scatter([x], [y], s=120, color=colour, edgecolors="black", zorder=3)
        axes.annotate(f"{name} (family {label})", (x, y), textcoords="offset points", xytext=(6, 6), fontsize=8)
    axes.set_xlabel("PCA 1 of the tokenizer features")
    axes.set_ylabel("PCA 2")
    axes.set_title(title, fontsize=9)
    axes.grid(alpha=0.3)
    figure.tight_layout()
    figure.savefig(path)

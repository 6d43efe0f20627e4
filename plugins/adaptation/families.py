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

from vqtouch.plugins.runtime.outputs import output_folder
from pydantic import Field, model_validator

from vqtouch.core import ConfigError, PluginHost
from vqtouch.plugins.utils.files import FileModel, read_model
from vqtouch.core.checkpoint import is_pretrained
from vqtouch.core.image_size import ImageSize
from vqtouch.plugins.utils.threads import on_one_thread
from vqtouch.plugins.data.sensor_folders import folder_of, load_sensor_folder
from vqtouch.plugins.tokenizer import TOKENIZER_FILES, tokenizer_digest

FeatureKind = Literal["pooled", "codes"]


@on_one_thread  # the families and assignments built on them must not depend on the thread count
@torch.no_grad()
def image_features(
    tokenizer: Any, images_B3HW: torch.Tensor, kind: FeatureKind = "pooled", batch_size: int = 32
) -> torch.Tensor:
    """Tokenizer features (B, F) of images in [0, 1] (float64; see the module docstring)."""
    if kind not in ("pooled", "codes"):
        raise ValueError(f"feature kind {kind!r}: expected 'pooled' or 'codes'")
    rows = []
    for chunk in images_B3HW.split(batch_size):
        chunk = chunk.to(tokenizer.device)
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


@on_one_thread
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


def sensor_images(
    spec: str, host: PluginHost, *, count: int, image_size: ImageSize, seed: int = 0, files: list[Path] | None = None
) -> SensorImages:
    """The images of ``spec``: a folder of image files (the first ``count`` in natural order, or
    the given ``files`` of it), or a registered sensor family given by name or JSON
    (``{"name": "gelsight", "variant": {...}}``), which renders ``count`` procedural scenes
    (scene seed ``seed``)."""
    from vqtouch.core import BuildContext

    path = folder_of(spec)
    if path is not None:
        images = load_sensor_folder(path, host, image_size, count=count, files=files)
        return SensorImages(path.name, str(path), images)
    text = spec.strip()
    try:
        config = json.loads(text) if text.startswith("{") else {"name": text}
    except json.JSONDecodeError as exc:
        raise ConfigError(f"sensor {spec!r}: not a folder, a sensor name or valid JSON ({exc})") from None
    if not isinstance(config, dict) or "name" not in config:
        raise ConfigError(f'sensor {spec!r}: a JSON sensor needs a \'name\', e.g. {{"name": "gelsight"}}')
    if config["name"] not in host.registry("sensor_family").names():
        raise ConfigError(
            f"sensor {spec!r} is neither a folder nor a registered sensor family "
            f"({', '.join(host.registry('sensor_family').names())})"
        )
    sensor = host.build("sensor_family", config)
    dataset = host.build(
        "dataset",
        {"name": "procedural", "num_samples": count, "image_size": image_size, "seed": seed},
        BuildContext(image_size=image_size),
        sensor=sensor,
    )
    images = dataset.render_batch(list(range(count)))["tactile"]
    return SensorImages(sensor_label(config), json.dumps(config, sort_keys=True), images)


def registered_source(spec: str) -> str:
    """The source a clustering records for the registered sensor ``spec`` (name or JSON variant):
    its config as sorted JSON, so an unseen sensor can be kept out of its own family's data; ''
    for a folder of images or a spec that is not JSON."""
    if folder_of(spec) is not None:
        return ""
    spec = spec.strip()
    try:
        config = json.loads(spec) if spec.startswith("{") else {"name": spec}
    except json.JSONDecodeError:
        return ""
    return json.dumps(config, sort_keys=True)


def sensor_label(config: dict[str, Any]) -> str:
    """A short display name of a sensor config: ``gelsight``, ``gelsight/v3`` (variant seed 3), or
    ``gelsight*`` for other options."""
    if set(config) == {"name"}:
        return config["name"]
    if set(config) == {"name", "variant"} and isinstance(config["variant"], dict):
        return f"{config['name']}/v{config['variant'].get('seed', 0)}"
    return config["name"] + "*"


def family_sensor_specs(
    host: PluginHost, variants_per_family: int = 3, *, strength: float = 1.0, first_seed: int = 101
) -> list[str]:
    """Sensor specs (JSON) for clustering: every registered sensor family, then
    ``variants_per_family`` random environmental variants of each
    (:func:`vqtouch.sensors.environment_variant`, seeds ``first_seed``, ``first_seed + 1``, ...)."""
    from vqtouch.sensors import environment_variant

    specs = []  # canonical JSON (sorted keys), as a clustering records its sources
    for name in host.registry("sensor_family").names():
        specs.append(json.dumps({"name": name}, sort_keys=True))
        for seed in range(first_seed, first_seed + variants_per_family):
            variant = environment_variant(seed, strength).model_dump(mode="json")
            specs.append(json.dumps({"name": name, "variant": variant}, sort_keys=True))
    return specs


#: A family count chosen by silhouette is uncertain when another count scores within this of it.
SILHOUETTE_MARGIN = 0.05


def family_count_note(choice: dict[str, Any], chosen: int) -> str | None:
    """Why a family count chosen by silhouette (``clusterer.count_choice``) may be wrong, and how to
    fix it; None when it was given or clearly best.  Silhouette cannot score every sensor as its own
    family, so with as many sensors as the largest count tried (a few sensors and no variants of
    them) three distinct designs can only come out as two families."""
    if choice.get("chosen_by") != "silhouette":
        return None
    fix = "pass --families K (cluster.clusterer.num_families in a scene) to set the count"
    scores = {int(count): score for count, score in choice.get("silhouette", {}).items()}
    distinct = choice.get("distinct_rows", 0)
    if distinct >= 2 and distinct - 1 < choice.get("max_families", 0) and chosen == distinct - 1:
        return (
            f"family count uncertain: with {distinct} distinct sensors the silhouette can compare 2 to "
            f"{distinct - 1} families, never {distinct} (each sensor its own), and chose {chosen}; add variants "
            f"of each sensor (a scene's cluster.variants_per_family) or {fix}"
        )
    rivals = {count: score for count, score in scores.items() if count != chosen}
    if chosen in scores and rivals:
        runner_up = max(rivals, key=lambda count: rivals[count])
        if scores[chosen] - rivals[runner_up] < SILHOUETTE_MARGIN:
            return (
                f"family count uncertain: silhouette {scores[chosen]:.3f} for {chosen} families, "
                f"{rivals[runner_up]:.3f} for {runner_up} (within {SILHOUETTE_MARGIN}); {fix}"
            )
    return None


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
    choice = dict(getattr(clusterer, "count_choice", {}) or {})
    note = family_count_note(choice, clusterer.num_families)
    return {
        "family_count": {**choice, **({"uncertain": note} if note else {})},
        "within_family_spread": [round(value, 6) for value in spreads],
        "refusal_threshold": round(refusal_threshold(spreads, centroids), 6),
        "families": [
            [names[i] for i in range(len(names)) if int(labels[i]) == family]
            for family in range(clusterer.num_families)
        ],
        "sensor_family": {name: int(label) for name, label in zip(names, labels)},
        "family_distances": [[round(float(value), 6) for value in row] for row in distances],
        "sensor_to_family_distances": {
            name: [round(float(v), 6) for v in row] for name, row in zip(names, to_families)
        },
    }


#: An unseen sensor farther from every family mean than this many times the largest within-family
#: spread is refused (see :func:`assign_to_family`).
REFUSAL_FACTOR = 3.0


def within_family_spread(
    prototypes_SF: torch.Tensor, labels_S: torch.Tensor, centroids_KF: torch.Tensor
) -> list[float]:
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
    return {
        "family": None if refused else nearest,
        "nearest_family": nearest,
        "refused": refused,
        "distances": [round(float(v), 6) for v in distances],
        "margin": round(margin, 6),
        "threshold": round(threshold, 6),
    }


@dataclass
class UnseenSensor:
    """An assigned sensor for the plot: its name, image features, prototype and verdict (e.g. "family 1")."""

    name: str
    features: torch.Tensor
    prototype: torch.Tensor
    verdict: str


#: Labels sit on a pale box so that markers under them do not hide them.
LABEL_BOX = {"boxstyle": "round,pad=0.15", "facecolor": "white", "edgecolor": "none", "alpha": 0.85}


def families_figure(
    names: list[str],
    features_by_sensor: list[torch.Tensor],
    prototypes_SF: torch.Tensor,
    labels: list[int],
    title: str,
    unseen: list[UnseenSensor] = (),
) -> Any:
    """A 2-D PCA embedding (fitted on every clustered image feature) of the images (small points)
    and the prototypes (large markers, coloured by family, numbered); the numbers are keyed to the
    sensors' names by family in a legend beside the plot, as variants of one sensor sit on top of
    each other.  Unseen sensors are black stars labelled with where they were assigned.  No two
    labels overlap (:func:`separate_labels`)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from sklearn.decomposition import PCA

    everything = torch.cat(features_by_sensor).numpy()
    pca = PCA(n_components=min(2, everything.shape[1], len(everything)), random_state=0).fit(everything)
    figure = Figure(figsize=(9.5, 6), dpi=110, layout="constrained")
    FigureCanvasAgg(figure)
    axes = figure.add_subplot(1, 1, 1)
    colours = [f"C{label % 10}" for label in labels]
    for features, colour in zip(features_by_sensor, colours):
        points = pca.transform(features.numpy())
        axes.scatter(
            points[:, 0], points[:, 1] if points.shape[1] > 1 else 0 * points[:, 0], s=6, alpha=0.3, color=colour
        )
    texts = []
    centres = pca.transform(prototypes_SF.numpy())
    for number, ((x, *rest), colour) in enumerate(zip(centres, colours), start=1):
        y = rest[0] if rest else 0.0
        axes.scatter([x], [y], s=120, color=colour, edgecolors="black", zorder=3)
        texts.append(
            axes.annotate(
                str(number), (x, y), textcoords="offset points", xytext=(8, 5), fontsize=8, zorder=6, bbox=LABEL_BOX
            )
        )
    texts += _plot_unseen(axes, pca, unseen)
    _family_legend(axes, names, labels)
    axes.set_xlabel("PCA 1 of the tokenizer features")
    axes.set_ylabel("PCA 2")
    axes.set_title(title, fontsize=9)
    axes.grid(alpha=0.3)
    separate_labels(figure, texts)
    return figure


def _plot_unseen(axes: Any, pca: Any, unseen: list[UnseenSensor]) -> list[Any]:
    """The unseen sensors' images and black-star prototypes, labelled with their verdicts; returns the labels."""
    texts = []
    for sensor in unseen:
        points = pca.transform(sensor.features.numpy())
        axes.scatter(
            points[:, 0], points[:, 1] if points.shape[1] > 1 else 0 * points[:, 0], s=6, alpha=0.3, color="black"
        )
        x, *rest = pca.transform(sensor.prototype.unsqueeze(0).numpy())[0]
        y = rest[0] if rest else 0.0
        axes.scatter([x], [y], s=260, marker="*", color="black", zorder=4)
        texts.append(
            axes.annotate(
                f"{sensor.name} (unseen: {sensor.verdict})",
                (x, y),
                textcoords="offset points",
                xytext=(7, -12),
                fontsize=8,
                fontweight="bold",
                zorder=6,
                bbox=LABEL_BOX,
            )
        )
    return texts


def _family_legend(axes: Any, names: list[str], labels: list[int]) -> None:
    """The legend beside the plot keying the prototypes' numbers to the sensors' names, by family."""
    from matplotlib.lines import Line2D

    members: dict[int, list[str]] = {}
    for number, (name, label) in enumerate(zip(names, labels), start=1):
        members.setdefault(label, []).append(f"{number} {name}")
    keys = [
        Line2D(
            [],
            [],
            marker="o",
            linestyle="",
            markersize=9,
            color=f"C{family % 10}",
            markeredgecolor="black",
            label=f"family {family}: {', '.join(members[family])}",
        )
        for family in sorted(members)
    ]
    axes.legend(handles=keys, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, title="sensors", frameon=False)


def separate_labels(figure: Any, texts: list[Any], gap_px: float = 1.0) -> None:
    """Move annotation texts down, one line at a time, until none overlaps an earlier one (in drawing
    order) on the rendered figure."""
    figure.canvas.draw()  # positions depend on the final layout
    renderer = figure.canvas.get_renderer()
    placed: list[Any] = []
    for text in texts:
        for _ in range(100):
            box = text.get_window_extent(renderer)
            if not any(box.overlaps(other) for other in placed):
                break
            x, y = text.get_position()  # offset points
            text.set_position((x, y - (box.height + gap_px) * 72 / figure.dpi))
        placed.append(text.get_window_extent(renderer).expanded(1.0, 1.0))


def plot_families(
    names: list[str],
    features_by_sensor: list[torch.Tensor],
    prototypes_SF: torch.Tensor,
    labels: list[int],
    path: Path,
    title: str,
    unseen: list[UnseenSensor] = (),
) -> None:
    """Write :func:`families_figure` to ``path``."""
    families_figure(names, features_by_sensor, prototypes_SF, labels, title, unseen).savefig(path)


#: What ``vqtouch cluster`` writes into its output folder (and ``vqtouch adapt`` reads back).
CLUSTER_JSON, CLUSTERER_FILE, FAMILIES_PNG = "cluster.json", "clusterer.safetensors", "families.png"


@dataclass
class SensorFamilies:
    """Sensors grouped into families by one tokenizer's features.

    ``summary`` is what ``cluster.json`` holds (families, members and their sources, the distance
    matrices, the refusal threshold, how the features were computed); ``clusterer`` is the fitted
    clusterer plugin (family means); ``features`` are the per-image features of each sensor, kept
    for the plot (None when read back from a folder).
    """

    summary: dict[str, Any]
    clusterer: Any
    prototypes_SF: torch.Tensor
    features: list[torch.Tensor] | None = None

    @property
    def names(self) -> list[str]:
        """The clustered sensors' display names."""
        return [sensor["name"] for sensor in self.summary["sensors"]]

    def members(self, family: int) -> list[dict[str, Any]]:
        """The sensors (name, source, images) of ``family``."""
        return [sensor for sensor in self.summary["sensors"] if self.summary["sensor_family"][sensor["name"]] == family]

    def unseen(
        self, tokenizer: Any, name: str, images_B3HW: torch.Tensor, threshold: float | None = None
    ) -> tuple[dict[str, Any], UnseenSensor]:
        """Assign an unseen sensor's images (its prototype computed exactly as the members' were):
        the assignment and the sensor as the plot shows it."""
        features = image_features(tokenizer, images_B3HW, self.summary["features"])
        prototype = sensor_prototype(features, self.summary["refine_steps"], self.summary["keep"])
        assigned = self.assign(prototype, threshold)
        verdict = "refused" if assigned["refused"] else f"family {assigned['family']}"
        return assigned, UnseenSensor(name, features, prototype, verdict)

    def assign(self, prototype_F: torch.Tensor, threshold: float | None = None) -> dict[str, Any]:
        """:func:`assign_to_family` with the fitted threshold unless one is given."""
        return assign_to_family(
            self.clusterer, prototype_F, self.summary["refusal_threshold"] if threshold is None else threshold
        )


def fit_families(
    tokenizer: Any,
    specs: list[str],
    host: PluginHost,
    *,
    clusterer: Any,
    images: int = 64,
    image_size: ImageSize = 64,
    features: FeatureKind = "pooled",
    refine_steps: int = 3,
    keep: float = 0.8,
    seed: int = 0,
    tokenizer_source: str = "",
    report: Any = print,
) -> SensorFamilies:
    """Group the sensors ``specs`` (see :func:`sensor_images`) into families with ``clusterer``
    (a built clusterer plugin, fitted here) from ``tokenizer``'s ``features``; ``report`` is called
    with one line per sensor."""
    if len(specs) < 2:
        raise ConfigError("give at least two sensors to group into families")
    repeated = sorted({spec for spec in specs if specs.count(spec) > 1})
    if repeated:
        raise ConfigError(
            f"sensor {repeated[0]} is listed {specs.count(repeated[0])} times: identical sensors give identical "
            "images, so the family spread (and the refusal threshold) would be 0; list each sensor once"
        )
    # Recorded absolute, with the weights' digest: the families are then recognised from any working
    # directory, and after the tokenizer folder is copied or moved.
    source = Path(tokenizer_source) if tokenizer_source and not is_pretrained(tokenizer_source) else None
    if source is not None and all((source / name).is_file() for name in TOKENIZER_FILES):
        tokenizer_source, digest = str(source.resolve()), tokenizer_digest(source)
    else:
        digest = None
    names: list[str] = []
    sensors, features_by_sensor, prototypes = [], [], []
    for spec in specs:
        sensor = sensor_images(spec, host, count=images, image_size=image_size, seed=seed)
        name = sensor.name if sensor.name not in names else f"{sensor.name}#{len(names)}"
        rows = image_features(tokenizer, sensor.images, features)
        names.append(name)
        sensors.append({"name": name, "source": sensor.source, "images": len(rows)})
        features_by_sensor.append(rows)
        prototypes.append(sensor_prototype(rows, refine_steps, keep))
        report(f"{name}: {len(rows)} images")
    prototypes_SF = torch.stack(prototypes)
    summary = {
        "tokenizer": tokenizer_source,
        **({"tokenizer_sha256": digest} if digest else {}),
        "features": features,
        "images_per_sensor": images,
        "image_size": image_size,
        "refine_steps": refine_steps,
        "keep": keep,
        "seed": seed,
        "clusterer": clusterer.vqtouch_spec.config.model_dump(mode="json"),
        "sensors": sensors,
        **cluster_prototypes(names, prototypes_SF, clusterer),
        "prototypes": {name: [round(float(v), 6) for v in row] for name, row in zip(names, prototypes_SF)},
    }
    return SensorFamilies(summary, clusterer, prototypes_SF, features_by_sensor)


def save_families(
    families: SensorFamilies,
    folder: Path,
    host: PluginHost,
    extra: dict[str, Any] | None = None,
    unseen: list[UnseenSensor] = (),
) -> Path:
    """Write ``cluster.json`` (the summary plus ``extra``), the fitted clusterer and, when the
    features are at hand, ``families.png`` (with the ``unseen`` sensors) into ``folder``; returns
    the JSON's path."""
    from vqtouch.core import save
    from vqtouch.core.checkpoint import atomic_write

    output_folder(folder)
    save(families.clusterer, folder / CLUSTERER_FILE, host=host)
    summary = {**families.summary, **(extra or {})}
    path = atomic_write(folder / CLUSTER_JSON, lambda tmp: tmp.write_text(json.dumps(summary, indent=2) + "\n"))
    if families.features is not None:
        count = len(summary["families"])
        plot_families(
            families.names,
            families.features,
            families.prototypes_SF,
            [summary["sensor_family"][name] for name in families.names],
            folder / FAMILIES_PNG,
            f"{count} families of {len(families.names)} sensors ({summary['features']} features, "
            f"{summary['clusterer']['name']})",
            unseen,
        )
    return path


class FamilySensor(FileModel):
    """One sensor of a ``cluster.json``."""

    name: str
    source: str = ""


class ClusterRecord(FileModel):
    """What is read back of a ``cluster.json`` (the rest of it is kept as written)."""

    tokenizer: str = ""
    features: str
    image_size: int | list[int]
    refine_steps: int
    keep: float
    refusal_threshold: float = Field(ge=0)
    clusterer: dict[str, Any]
    sensors: list[FamilySensor] = Field(min_length=2)
    families: list[list[str]]
    sensor_family: dict[str, int]
    prototypes: dict[str, list[float]]

    @model_validator(mode="after")
    def _every_sensor_has_a_prototype_and_family(self) -> ClusterRecord:
        for sensor in self.sensors:
            if sensor.name not in self.prototypes or sensor.name not in self.sensor_family:
                raise ValueError(f"sensor {sensor.name!r} has no prototype or family")
            if not 0 <= self.sensor_family[sensor.name] < len(self.families):
                raise ValueError(
                    f"sensor {sensor.name!r} is in family {self.sensor_family[sensor.name]}, which is not listed"
                )
        if len({len(row) for row in self.prototypes.values()}) > 1:
            raise ValueError("the prototypes have different lengths")
        return self


def load_families(folder: str | Path, host: PluginHost) -> SensorFamilies:
    """Families written by ``vqtouch cluster`` (or the ``cluster`` stage) into ``folder``."""
    from vqtouch.core import load

    folder = Path(folder)
    if not (folder / CLUSTER_JSON).is_file() or not (folder / CLUSTERER_FILE).is_file():
        raise ConfigError(
            f"{folder}: no sensor families here ({CLUSTER_JSON} and {CLUSTERER_FILE}); make them with "
            f"`vqtouch cluster --run TOKRUN --sensors ... --out {folder}`"
        )
    summary = read_model(folder / CLUSTER_JSON, ClusterRecord).model_dump()
    clusterer = load(folder / CLUSTERER_FILE, host=host)
    names = [sensor["name"] for sensor in summary["sensors"]]
    prototypes_SF = torch.tensor([summary["prototypes"][name] for name in names], dtype=torch.float64)
    return SensorFamilies(summary, clusterer, prototypes_SF)

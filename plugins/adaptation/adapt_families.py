"""The sensor families an adaptation assigns its unseen sensor to, and the family it adapts from:
the families saved by ``vqtouch cluster`` (fitted on the same tokenizer) or the registered sensor
families clustered now.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from vqtouch.core import ConfigError, PluginHost
from vqtouch.core.image_size import ImageSize
from vqtouch.plugins.tokenizer import TOKENIZER_FILES, tokenizer_digest

from .adapt_images import AdaptationRefused
from .families import SensorFamilies, save_families
from .stages_plugin import AdaptSettings

#: The folder of an adaptation's output that holds the families when it fitted them itself.
FAMILIES_FOLDER = "families"


def choose_family(
    families: SensorFamilies,
    tokenizer: Any,
    name: str,
    source: str,
    shots_N3HW: torch.Tensor,
    settings: AdaptSettings,
    host: PluginHost,
    out: Path,
    report: Any,
) -> tuple[dict[str, Any], int]:
    """The sensor's assignment and the family it adapts from (``settings.family`` when given); families
    fitted for this adaptation are written into ``out`` with the sensor.  Raises
    :class:`AdaptationRefused` when the sensor matches no family and none is named."""
    assignment, shown = families.unseen(tokenizer, name, shots_N3HW, settings.threshold)
    if families.features is not None:  # fitted for this adaptation (not read back): write them, with the sensor
        save_families(
            families, out / FAMILIES_FOLDER, host, {"assignments": {name: {"source": source, **assignment}}}, [shown]
        )
    family = assignment["family"]
    if settings.family is not None:
        if not 0 <= settings.family < len(families.summary["families"]):
            raise ConfigError(
                f"--family {settings.family}: the families are numbered 0 to {len(families.summary['families']) - 1}"
            )
        family = settings.family
    elif assignment["refused"]:
        nearest = assignment["nearest_family"]
        raise AdaptationRefused(
            f"{name} matches no sensor family: {assignment['distances'][nearest]:.4g} from the nearest (family "
            f"{nearest}: {', '.join(families.summary['families'][nearest])}), beyond the threshold "
            f"{assignment['threshold']:.4g}; cluster it with more sensors, raise --threshold, or name a family with "
            "--family"
        )
    report(
        f"{name}: family {family} ({', '.join(families.summary['families'][family])}); distances "
        f"{assignment['distances']}, margin {assignment['margin']:.4g}"
    )
    return assignment, family


def default_families(
    tokenizer: Any,
    host: PluginHost,
    *,
    image_size: ImageSize,
    tokenizer_source: str,
    exclude: str = "",
    clusterer: dict[str, Any] | None = None,
    variants_per_family: int = 3,
    images: int = 32,
    seed: int = 0,
    report: Any = print,
) -> SensorFamilies:
    """Families of every registered sensor family and ``variants_per_family`` environmental
    variants of each (:func:`.families.family_sensor_specs`), clustered with ``clusterer``
    (default: k-means, the family count by silhouette); the sensor whose source is ``exclude``
    (the unseen one) is left out."""
    from .families import family_sensor_specs, fit_families

    specs = [spec for spec in family_sensor_specs(host, variants_per_family) if spec != exclude]
    return fit_families(
        tokenizer,
        specs,
        host,
        clusterer=host.build("clusterer", clusterer or {"name": "kmeans"}),
        images=images,
        image_size=image_size,
        seed=seed,
        tokenizer_source=tokenizer_source,
        report=report,
    )


def families_to_adapt_from(
    tokenizer: Any, folder: Path, host: PluginHost, *, families: Path | None, where: str, exclude: str, seed: int
) -> SensorFamilies:
    """The families an adaptation assigns its target to: those saved in ``families`` (``where`` names
    them in the refusal when they were fitted on another tokenizer than the one in ``folder``), else the
    registered defaults, clustered now with ``tokenizer`` (:func:`default_families`)."""
    from .families import load_families

    if families is not None:
        loaded = load_families(families, host)
        check_same_tokenizer(loaded, folder, where)
        return loaded
    return default_families(
        tokenizer,
        host,
        image_size=tokenizer.autoencoder.vqtouch_spec.context.image_size,
        tokenizer_source=str(folder),
        exclude=exclude,
        seed=seed,
        report=lambda line: None,
    )


def check_same_tokenizer(families: SensorFamilies, tokenizer_folder: Path, where: str) -> None:
    """Refuse families fitted on another tokenizer's features: distances to them mean nothing."""
    fitted = families.summary.get("tokenizer", "")
    digest = families.summary.get("tokenizer_sha256")
    if digest and all((tokenizer_folder / name).is_file() for name in TOKENIZER_FILES):
        same = tokenizer_digest(tokenizer_folder) == digest
    else:  # families written before digests were recorded
        same = not fitted or Path(fitted).resolve() == tokenizer_folder.resolve()
    if not same:
        raise ConfigError(
            f"{where} were fitted on the features of {fitted}, not of {tokenizer_folder} (the tokenizer "
            "being adapted); run `vqtouch cluster` with this tokenizer, or adapt that one"
        )

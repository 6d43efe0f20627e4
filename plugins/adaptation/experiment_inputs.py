"""What the few-shot experiments (``vqtouch evaluate fewshot`` and ``evaluate mix-ratio``) set up
alike: how many held-out images score every arm, the families the arms mix from and the family each
seed adapts from."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Sequence

from vqtouch.core import ConfigError, PluginHost
from vqtouch.core.image_size import ImageSize
from vqtouch.plugins.data.sensor_folders import folder_of, sensor_folder_files

from .adapt_families import check_same_tokenizer, default_families
from .adapt_images import target_images
from .families import SensorFamilies, load_families, registered_source, save_families


def held_out_count(target: str, counts: Sequence[int], eval_images: int, host: PluginHost, flag: str = "--n") -> int:
    """How many held-out images score every arm: ``eval_images``, or for a folder as many as the
    largest N leaves (its shuffle's last ones are held out; every N must leave the same ones).
    A one-line ConfigError naming ``flag`` (the option that gave the counts) when the folder cannot
    spare the largest N plus one held-out image."""
    path = folder_of(target)
    if path is None:
        return eval_images
    images = len(sensor_folder_files(path, host))
    if max(counts) + 1 > images:
        usable = f"the largest usable {flag} is {images - 1}" if images > 1 else "few-shot needs at least 2 images"
        raise ConfigError(
            f"{flag} {max(counts)}: the folder {path} holds {images} images; {usable} (the rest are held "
            "out to score every arm)"
        )
    return min(eval_images, images - max(counts))


def families_for(
    families: str | Path | None,
    tokenizer: Any,
    folder: Path,
    target: str,
    host: PluginHost,
    out: Path,
    image_size: ImageSize,
) -> tuple[SensorFamilies, str]:
    """The families the fine-tuned arms mix from and where they came from: ``families`` (a cluster
    output of this tokenizer), or the registered sensor families and 3 variants of each clustered
    once (written to ``out/families`` and read back, so no arm writes them again)."""
    if families:
        loaded = load_families(families, host)
        check_same_tokenizer(loaded, folder, f"the families in {families}")
        return loaded, str(families)
    exclude = registered_source(target)
    fitted = default_families(
        tokenizer, host, image_size=image_size, tokenizer_source=str(folder), exclude=exclude, report=lambda line: None
    )
    save_families(fitted, out / "families", host)
    return load_families(out / "families", host), f"{out / 'families'} (registered sensor families, 3 variants each)"


def assign_seed_family(
    fitted: SensorFamilies,
    tokenizer: Any,
    target: str,
    host: PluginHost,
    *,
    shots: int,
    eval_images: int,
    image_size: ImageSize,
    seed: int,
) -> tuple[str, str, dict[str, Any]]:
    """The family one seed's arms adapt from, assigned from that seed's ``shots`` images of the
    sensor: its nearest family when the assignment is refused (the entry says so).  Returns the
    sensor's name, its source and the entry ``{"seed", "family", "members", "refused",
    "nearest_family", "margin", "threshold"}``."""
    name, source, shots_N, _ = target_images(
        target, host, shots=shots, eval_images=eval_images, image_size=image_size, seed=seed
    )
    assigned, _ = fitted.unseen(tokenizer, name, shots_N)
    family = assigned["nearest_family"] if assigned["refused"] else assigned["family"]
    return (
        name,
        source,
        {
            "seed": seed,
            "family": family,
            "members": fitted.summary["families"][family],
            **{key: assigned[key] for key in ("refused", "nearest_family", "margin", "threshold")},
        },
    )


def report_seed_family(
    fitted: SensorFamilies,
    tokenizer: Any,
    target: str,
    host: PluginHost,
    *,
    shots: int,
    eval_images: int,
    image_size: ImageSize,
    seed: int,
    report: Callable[[str], None],
) -> tuple[str, str, dict[str, Any]]:
    """:func:`assign_seed_family`, with a line to ``report`` naming the family and its members."""
    name, source, assignment = assign_seed_family(
        fitted, tokenizer, target, host, shots=shots, eval_images=eval_images, image_size=image_size, seed=seed
    )
    report(
        f"seed {seed}: {name} -> family {assignment['family']} ({', '.join(assignment['members'])})"
        + (", nearest: the assignment was refused" if assignment["refused"] else "")
    )
    return name, source, assignment

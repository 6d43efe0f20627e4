"""The ``vqtouch evaluate pairs`` command's handler and what it needs (its parser is in commands.py):
pair two folders of images by id and score them under a named protocol."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import torch

from vqtouch.core import ConfigError, PluginHost
from vqtouch.core.checkpoint import atomic_write
from vqtouch.core.image_size import image_hw
from vqtouch.plugins.utils.images import ImageLoader
from vqtouch.plugins.data.readers import is_image_file, read_image_size

from .protocols import get_protocol, pair_by_id


def images_by_id(folder: Path) -> dict[str, Path]:
    """Every image file below ``folder`` by id (relative path without extension); a ConfigError for
    a missing or image-less folder, or two files with one id (``a.png`` and ``a.jpg``)."""

    if not folder.is_dir():
        raise ConfigError(f"{folder} is not a folder of images")
    found: dict[str, Path] = {}
    for path in sorted(folder.rglob("*")):
        if path.is_file() and is_image_file(path) and not any(part.startswith(".") for part in path.parts):
            key = path.relative_to(folder).with_suffix("").as_posix()
            if key in found:
                raise ConfigError(f"{found[key]} and {path} have the same id {key!r}; keep one of them")
            found[key] = path
    if not found:
        raise ConfigError(f"{folder} holds no image files (png, jpg, ...)")
    return found


def load_pairs(
    generated: dict[str, Path], real: dict[str, Path], ids: list[str], image_size: int | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """The paired images, both at ``image_size`` x ``image_size`` (None: the first generated image's size),
    resized whole (no crop), bicubic as Pillow resizes."""

    if image_size is None:
        width, height = read_image_size(generated[ids[0]])
        size: Any = (height, width)
    else:
        size = image_size
    loader = ImageLoader(size=size, crop="stretch")
    return (
        torch.stack([loader.load(generated[key]) for key in ids]),
        torch.stack([loader.load(real[key]) for key in ids]),
    )


def evaluate_pairs(
    generated_folder: Path,
    real_folder: Path,
    protocol_name: str,
    host: PluginHost,
    overrides: dict[str, dict[str, Any]] | None = None,
    batch_size: int = 64,
) -> dict[str, Any]:
    """Score ``generated_folder`` against ``real_folder`` under the named protocol; returns the result
    (protocol, its description, pair count, image size, scores and any skipped metrics)."""
    protocol = get_protocol(protocol_name)
    generated, real = images_by_id(generated_folder), images_by_id(real_folder)
    ids = pair_by_id(generated, real)
    metrics = protocol.build_metrics(host, overrides)
    metrics.reset()
    size = None
    for start in range(0, len(ids), batch_size):
        generated_B3HW, real_B3HW = load_pairs(generated, real, ids[start : start + batch_size], protocol.image_size)
        size = tuple(generated_B3HW.shape[-2:])
        metrics.update(generated_B3HW, real_B3HW)
    return {
        "protocol": protocol.name,
        "protocol_description": protocol.description,
        "pairs": len(ids),
        "image_size": list(image_hw(size)),
        "generated": str(generated_folder),
        "real": str(real_folder),
        **metrics.scores(),
    }


def cmd_evaluate_pairs(args: argparse.Namespace) -> int:
    """``vqtouch evaluate pairs``: score the folders, print the result and write it to ``--out``."""
    overrides: dict[str, dict[str, Any]] = {}
    protocol = get_protocol(args.protocol)
    names = {metric["name"] for metric in protocol.metrics}
    if args.lpips_weights and "lpips" in names:
        overrides["lpips"] = {"weights": args.lpips_weights}
    result = evaluate_pairs(Path(args.generated), Path(args.real), args.protocol, args.host, overrides)
    text = json.dumps(result, indent=2) + "\n"
    if args.out:
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(out, lambda tmp: tmp.write_text(text))
    print(text, end="")
    for name, reason in result.get("skipped", {}).items():
        print(f"skipped {name}: {reason}")
    return 0

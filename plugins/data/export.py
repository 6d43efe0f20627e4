"""Writing dataset samples to a browsable folder that the ``image_folder`` reader reads back.

Layout: ``tactile/<id>.png``, ``visual/<id>.png`` (when the samples pair a visual image),
``index.csv`` (``path,label,visual,class_name,text,sensor`` and ``depth_mm`` for procedural
scenes), ``classes.txt`` and ``preview.png`` (tactile | visual pairs).
"""

from __future__ import annotations

import csv
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import torch

from vqtouch.core.checkpoint import atomic_write
from vqtouch.plugins.utils.images import image_grid, save_png
from vqtouch.plugins.utils.progress import progress
from vqtouch.plugins.training.batches import collate_samples


def sample_batches(dataset: Any, indices: list[int], batch_size: int) -> Iterable[dict[str, Any]]:
    """The samples ``indices`` of ``dataset`` in batches of ``batch_size``, collated (tensors stacked,
    strings in lists)."""
    for first in range(0, len(indices), batch_size):
        chunk = indices[first:first + batch_size]
        # The procedural dataset renders a batch at once; any other dataset is read sample by sample.
        render_batch = getattr(dataset, "render_batch", None)
        yield render_batch(chunk) if render_batch else collate_samples([dataset[i] for i in chunk])


def export_samples(dataset: Any, indices: Iterable[int], out: Path, *, batch_size: int = 32,
                   preview_count: int = 16) -> dict[str, Any]:
    """Write the samples ``indices`` of ``dataset`` under ``out``; returns what was written
    (dataset config when it has one, sample count, seconds, samples/s)."""
    indices = list(indices)
    if not indices:
        raise ValueError("export_samples needs at least one sample index")
    (out / "tactile").mkdir(parents=True, exist_ok=True)
    rows, previews = [], []
    start = time.perf_counter()
    bar = progress(total=len(indices), desc="rendering", unit="img")
    for batch in sample_batches(dataset, indices, batch_size):
        for k, sample_id in enumerate(batch["id"]):
            name = str(sample_id).replace("/", "_")
            save_png(batch["tactile"][k], out / "tactile" / f"{name}.png")
            label = int(batch["label"][k])
            row = {"path": f"tactile/{name}.png", "label": label}
            if "visual" in batch:
                (out / "visual").mkdir(exist_ok=True)
                save_png(batch["visual"][k], out / "visual" / f"{name}.png")
                row["visual"] = f"visual/{name}.png"
            row |= {"class_name": dataset.class_names[label] if label >= 0 and dataset.class_names else "",
                    "text": batch["text"][k], "sensor": batch["sensor"][k]}
            if "depth_mm" in batch:
                row["depth_mm"] = f"{float(batch['depth_mm'][k]):.4f}"
            rows.append(row)
            if len(previews) < preview_count:
                previews.append((batch["tactile"][k], batch["visual"][k] if "visual" in batch else batch["tactile"][k]))
        bar.update(len(batch["id"]))
    bar.close()
    seconds = time.perf_counter() - start

    def write_index(tmp: Path) -> None:
        with open(tmp, "w", newline="", encoding="utf-8") as handle:
            writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)

    atomic_write(out / "index.csv", write_index)
    atomic_write(out / "classes.txt", lambda tmp: tmp.write_text("\n".join(dataset.class_names) + "\n"))
    save_png(image_grid(torch.stack([image for pair in previews for image in pair]), columns=8), out / "preview.png")
    config = getattr(dataset, "config", None)
    return {"dataset": config.model_dump(mode="json") if config is not None else type(dataset).__name__,
            "samples": len(rows), "seconds": round(seconds, 2), "images_per_second": round(len(rows) / seconds, 1)}

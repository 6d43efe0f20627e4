"""Rendering cost of the embedded procedural data, per sensor family and resolution.

Run:  .venv/bin/python bench/bench_render.py [--device cpu|cuda] [--repeats 3]

For 64, 128 and 256 px it times, on the same samples: the object geometry, the visual
(camera) image, the tactile render (one call per sample, as the dataset does, and one
batched call), and the whole ``render_batch`` of the dataset.  Each figure is the best of
``--repeats`` runs; the table also gives each resolution's cost relative to 64 px, measured
in the same run (absolute numbers move with the machine's load, ratios much less).
"""

from __future__ import annotations

import argparse
import time

import torch

from vqtouch.core import load_plugins
from vqtouch.sensors.camera import render_visual
from vqtouch.sensors.objects import OBJECT_CLASSES, sample_contact

SAMPLES = {64: 48, 128: 24, 256: 12}


def best_rate(function, count: int, repeats: int) -> float:
    """Items per second of the fastest of ``repeats`` runs of ``function`` (which handles ``count`` items)."""
    function()  # warm-up: caches, allocator, first-call overheads
    best = min(_timed(function) for _ in range(repeats))
    return count / best


def _timed(function) -> float:
    start = time.perf_counter()
    function()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu", help="device for the sensor render (cpu or cuda)")
    parser.add_argument("--repeats", type=int, default=3, help="runs per measurement; the best is kept")
    args = parser.parse_args()
    torch.set_num_threads(torch.get_num_threads())
    host = load_plugins(autoload=False)
    device = torch.device(args.device)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, sensor render on {device}")
    header = (
        f"{'sensor':14s} {'size':>5s} {'geometry/s':>11s} {'visual/s':>9s} {'tactile/s':>10s} "
        f"{'batched/s':>10s} {'samples/s':>10s} {'cost vs 64px':>13s}"
    )
    print(header)
    print("-" * len(header))
    for sensor_name in host.registry("sensor_family").names():
        sensor = host.build("sensor_family", sensor_name).to(device)
        baseline = None
        for size, count in SAMPLES.items():
            generator = torch.Generator().manual_seed(0)
            classes = [(OBJECT_CLASSES[i % len(OBJECT_CLASSES)], i % len(OBJECT_CLASSES)) for i in range(count)]
            contacts = [sample_contact(c, label, generator, size, sensor.field_of_view_mm) for c, label in classes]
            heights = torch.stack([c.indentation_mm_HW for c in contacts]).to(device)
            geometry = best_rate(
                lambda: [
                    sample_contact(c, label, torch.Generator().manual_seed(1), size, sensor.field_of_view_mm)
                    for c, label in classes
                ],
                count,
                args.repeats,
            )
            visual = best_rate(
                lambda: [
                    render_visual(c, contact, torch.Generator().manual_seed(2), sensor.field_of_view_mm)
                    for (c, _), contact in zip(classes, contacts)
                ],
                count,
                args.repeats,
            )
            with torch.no_grad():
                single = best_rate(lambda: [sensor.render(h[None]) for h in heights], count, args.repeats)
                batched = best_rate(lambda: sensor.render(heights), count, args.repeats)
            dataset = host.build(
                "dataset",
                {"name": "procedural", "num_samples": count, "image_size": size, "cache": False},
                sensor=sensor,
            )
            whole = best_rate(lambda: dataset.render_batch(list(range(count))), count, args.repeats)
            baseline = baseline or whole
            print(
                f"{sensor_name:14s} {size:5d} {geometry:11.1f} {visual:9.1f} {single:10.1f} {batched:10.1f} "
                f"{whole:10.1f} {baseline / whole:12.1f}x"
            )


if __name__ == "__main__":
    main()

"""Where `vqtouch data leakage`'s default threshold comes from: the share of held-out images with a
"near-duplicate" in training, at several thresholds, for splits that leak and splits that do not.

Run:  .venv/bin/python bench/leakage_threshold.py [--samples 1000] [--frames 12 30]

For GelSight and GelSight Mini it renders video-like datasets (each recording: one procedural
contact pressed in over ``frames`` frames, from 55% to 100% of its depth) and holds out 10% of
them twice: by frame (the leaking split of Touch and Go and HCT) and by recording (vqtouch's split
for readers that know recordings).  The independent procedural data is the third row.  A good
threshold flags nearly every frame split and few recording splits; the distance is the mean
absolute difference in 8-bit levels at 32 x 32 px (:mod:`vqtouch.plugins.data.leakage`).
"""

from __future__ import annotations

import argparse
from typing import Any

import torch

from vqtouch.core import TactileDataset, load_plugins
from vqtouch.plugins.utils.splits import split_dataset
from vqtouch.plugins.data.leakage import check_leakage, read_thumbnails
from vqtouch.plugins.data.procedural import sample_generator
from vqtouch.sensors.objects import OBJECT_CLASSES, sample_contact

THRESHOLDS = (0.1, 0.2, 0.25, 0.3, 0.4, 0.5, 0.75, 1.0)


class PressRecordings(TactileDataset):
    """``recordings`` videos of ``frames`` frames: one contact each, pressed deeper frame by frame."""

    split_unit = "recording"

    def __init__(self, sensor: Any, recordings: int, frames: int, size: int = 64, grouped: bool = True) -> None:
        self.frames, self.grouped = frames, grouped
        extent = sensor.imaged_extent_mm(size, size)
        self.images = []
        for recording in range(recordings):
            generator = sample_generator(99, recording)
            label = int(torch.randint(0, len(OBJECT_CLASSES), (1,), generator=generator))
            contact = sample_contact(OBJECT_CLASSES[label], label, generator, size, extent, (0.2, 1.0))
            top = contact.surface_mm_HW.max()
            for frame in range(frames):
                depth = contact.depth_mm * (0.55 + 0.45 * frame / (frames - 1))
                indentation = (contact.surface_mm_HW - (top - depth)).clamp_min(0)
                noise = torch.Generator().manual_seed(recording * 1000 + frame)
                self.images.append(sensor.render(indentation[None], generator=noise)[0])

    def __len__(self) -> int:
        return len(self.images)

    def __getitem__(self, index: int) -> dict[str, Any]:
        return {
            "tactile": self.images[index],
            "label": -1,
            "text": "",
            "sensor": "bench",
            "id": f"r{index // self.frames:04d}/f{index % self.frames:03d}",
        }

    def split_groups(self) -> list[str] | None:
        """The recording of each frame, or None to split frame by frame (the leaking split)."""
        return [f"r{index // self.frames:04d}" for index in range(len(self))] if self.grouped else None


def flagged_shares(dataset: TactileDataset) -> tuple[str, list[float]]:
    """The split's unit and, per threshold, the share of held-out images within it of a training image."""
    train, held_out = split_dataset(dataset, 0.1, 0)
    thumbnails = read_thumbnails(dataset)
    distances_M = check_leakage(thumbnails.select(train.indices), thumbnails.select(held_out.indices), 0.0).distance_M
    return held_out.split_unit, [round(float((distances_M <= threshold).float().mean()), 3) for threshold in THRESHOLDS]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=1000, help="images per dataset")
    parser.add_argument("--frames", type=int, nargs="+", default=[12, 30], help="frames per recording")
    args = parser.parse_args()
    host = load_plugins()
    print("| sensor | data | split by | " + " | ".join(f"<= {t:g}" for t in THRESHOLDS) + " |")
    print("|---|---|---|" + "---|" * len(THRESHOLDS))
    for sensor_name in ("gelsight", "gelsight_mini"):
        sensor = host.build("sensor_family", sensor_name)
        rows = [
            ("procedural", host.build("dataset", {"name": "procedural", "num_samples": args.samples}, sensor=sensor))
        ]
        for frames in args.frames:
            recordings = PressRecordings(sensor, args.samples // frames, frames)
            rows.append((f"video, {frames} frames/recording", recordings))
        for data, dataset in rows:
            for grouped in (False, True) if isinstance(dataset, PressRecordings) else (True,):
                dataset.grouped = grouped  # the same images, split by frame then by recording
                unit, shares = flagged_shares(dataset)
                print(f"| {sensor_name} | {data} | {unit} | " + " | ".join(f"{share:.0%}" for share in shares) + " |")


if __name__ == "__main__":
    main()

"""Near-duplicates between training and held-out images: the check behind ``vqtouch data leakage``.

Tactile datasets are mostly video frames, and a split by frame puts near-identical frames of one
recording on both sides, which inflates every held-out score.  This check finds such pairs from
the pixels alone: every image is resized to a small common size (``COMPARE_SIZE`` a side), and
for each held-out ("test") image its nearest training image is found by the mean absolute
difference of their pixels, in 8-bit grey levels (0 to 255).  A test image whose nearest
training image is at most ``threshold`` away has a near-duplicate in training.

The default threshold, ``DEFAULT_THRESHOLD`` = 0.25 levels, is measured on rendered GelSight and
GelSight Mini images (64 px, compared at 32 x 32; noise-free renders).  A video-like dataset of
1000 frames (recordings of one procedural contact pressed from 55 % to 100 % of its depth, 12 or
30 frames each) and the procedural dataset (1000 independent samples) were split as the stages
split them (val_fraction 0.1, seed 0); the share of held-out images flagged, GelSight / Mini:

=========  ======================  ======================  ===========================
threshold  video, split by frame   video, by recording     procedural (independent)
=========  ======================  ======================  ===========================
0.2        81 / 69 % (12 frames)   0 / 0 %                 0 / 2 %
0.25       97 / 82 % (12 frames)   15 / 14 % (12 frames)   4 / 4 %
0.5        100 / 100 %             53 / 62 % (12 frames)   16 / 14 %
=========  ======================  ======================  ===========================

(30-frame recordings: 100 % by frame and 0 % by recording at all three.)  The flags at larger
thresholds are faint presses of different contacts, which differ in few pixels on one gel
background; 0.25 keeps them rare while leaving a margin for the noise of real frames.  A sensor
with camera noise has a noise floor below which no two images come: rendered DIGIT images (noise
7/255 at 64 px) are about 4 levels apart even for one contact, so raise the threshold above the
floor that the printed distance quantiles show.

Distances are computed in float32 chunks of at most ``DISTANCE_CHUNK_ELEMENTS`` (16 MB) whatever
the two sets' sizes, so memory is the thumbnails (12 KB an image at 32 x 32) plus one chunk; the
time grows with the product of the sizes: 200 test against 10,000 training images took 7.5 s on
one CPU core (11 MB beyond the thumbnails), so 10,000 against 10,000 take minutes.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F

from vqtouch.core import ConfigError, TactileDataset
from vqtouch.core.image_size import size_text
from vqtouch.plugins.utils.progress import progress

from .export import sample_batches
from .leakage_defaults import COMPARE_SIZE, DEFAULT_THRESHOLD
from vqtouch.plugins.utils.images import image_grid

#: Images read per step.
READ_BATCH = 64
#: Distances computed at once (float32): bounds memory whatever the two sets' sizes.
DISTANCE_CHUNK_ELEMENTS = 1 << 22
#: Quantiles of the nearest-training distance that a report prints.
QUANTILES = (0.0, 0.01, 0.05, 0.5, 1.0)


@dataclass(frozen=True)
class Thumbnails:
    """A dataset's tactile images at the comparison size, one flattened row each, with their ids."""

    pixels_NP: torch.Tensor
    ids: list[str]
    #: (height, width) of the images the dataset returned, before resizing.
    image_hw: tuple[int, int]
    #: Side of the square the images were resized to.
    size: int

    def select(self, indices: Sequence[int]) -> Thumbnails:
        """The thumbnails of samples ``indices``, in that order."""
        return Thumbnails(
            self.pixels_NP[list(indices)], [self.ids[index] for index in indices], self.image_hw, self.size
        )


def resize_images(images_B3HW: torch.Tensor, size_hw: tuple[int, int]) -> torch.Tensor:
    """Images resized to ``size_hw`` with antialiasing (unchanged when already that size)."""
    if tuple(images_B3HW.shape[-2:]) == tuple(size_hw):
        return images_B3HW.float()
    return F.interpolate(images_B3HW.float(), size=size_hw, mode="bilinear", antialias=True, align_corners=False)


def read_thumbnails(dataset: TactileDataset, size: int = COMPARE_SIZE, desc: str = "reading images") -> Thumbnails:
    """Every tactile image of ``dataset`` at ``size`` x ``size``, as float32 rows in [0, 1]."""
    if len(dataset) == 0:
        raise ConfigError(f"{_dataset_name(dataset)} has no samples: nothing to compare")
    rows, ids, first_hw = [], [], None
    # The bar shows only when reading takes more than a moment.
    with progress(total=len(dataset), desc=desc, unit="img", delay=1.0) as bar:
        for batch in sample_batches(dataset, list(range(len(dataset))), READ_BATCH):
            tactile = batch["tactile"]
            first_hw = first_hw or tuple(tactile.shape[-2:])
            rows.append(resize_images(tactile, (size, size)).flatten(1))
            ids += [str(sample_id) for sample_id in batch["id"]]
            bar.update(len(tactile))
    return Thumbnails(torch.cat(rows), ids, first_hw, size)


def nearest_neighbours(
    test_MP: torch.Tensor, train_NP: torch.Tensor, desc: str = "comparing"
) -> tuple[torch.Tensor, torch.Tensor]:
    """For each row of ``test_MP``, the index of its nearest row of ``train_NP`` and their mean
    absolute difference, in units of the rows (float32, in chunks of bounded size)."""
    if train_NP.shape[0] == 0 or test_MP.shape[0] == 0:
        raise ConfigError("nothing to compare: the training or the test side has no images")
    rows_per_chunk = max(1, DISTANCE_CHUNK_ELEMENTS // train_NP.shape[0])
    train_NP = train_NP.float()
    distances, indices = [], []
    with progress(total=test_MP.shape[0], desc=desc, unit="img", delay=1.0) as bar:
        for start in range(0, test_MP.shape[0], rows_per_chunk):
            chunk = test_MP[start : start + rows_per_chunk].float()
            best, where = torch.cdist(chunk, train_NP, p=1).min(dim=1)
            distances.append(best / train_NP.shape[1])
            indices.append(where)
            bar.update(len(chunk))
    return torch.cat(indices), torch.cat(distances)


@dataclass(frozen=True)
class LeakageReport:
    """Each test image's nearest training image and their distance, and the verdict at a threshold.

    Distances are mean absolute differences in 8-bit levels (0 to 255) of the images at
    ``compare_size`` x ``compare_size``; a test image at most ``threshold`` from its nearest
    training image has a near-duplicate in training.
    """

    test_ids: list[str]
    train_ids: list[str]
    nearest_M: torch.Tensor
    distance_M: torch.Tensor
    threshold: float
    compare_size: int

    @property
    def near_duplicate_count(self) -> int:
        """How many test images have a near-duplicate in training."""
        return int((self.distance_M <= self.threshold).sum())

    @property
    def near_duplicate_fraction(self) -> float:
        """The share of test images that have a near-duplicate in training."""
        return self.near_duplicate_count / len(self.test_ids)

    def closest(self, count: int | None = None) -> list[tuple[int, int, float]]:
        """(test index, train index, distance) of the ``count`` closest pairs (all when None), closest first."""
        order = torch.argsort(self.distance_M, stable=True)[:count].tolist()
        return [(test, int(self.nearest_M[test]), float(self.distance_M[test])) for test in order]

    def summary(self) -> str:
        """The verdict in one line."""
        return (
            f"{self.near_duplicate_count} of {len(self.test_ids)} test images have a near-duplicate in train "
            f"(threshold {self.threshold:g})"
        )

    def quantiles(self) -> dict[str, float]:
        """Quantiles of the distance from a test image to its nearest training image."""
        values = torch.quantile(self.distance_M.double(), torch.tensor(QUANTILES, dtype=torch.float64)).tolist()
        return {_quantile_name(q): round(value, 3) for q, value in zip(QUANTILES, values)}

    def to_json(self) -> dict[str, Any]:
        """Everything the report knows, for ``leakage.json``: each test image's nearest training image,
        closest first."""
        return {
            "metric": f"mean absolute difference of 8-bit levels at {self.compare_size}x{self.compare_size}",
            "threshold": self.threshold,
            "test_images": len(self.test_ids),
            "train_images": len(self.train_ids),
            "near_duplicates": self.near_duplicate_count,
            "near_duplicate_fraction": round(self.near_duplicate_fraction, 6),
            "distance_quantiles": self.quantiles(),
            "nearest": [
                {
                    "test_id": self.test_ids[test],
                    "train_id": self.train_ids[train],
                    "distance": round(distance, 4),
                    "near_duplicate": distance <= self.threshold,
                }
                for test, train, distance in self.closest()
            ],
        }


def check_leakage(train: Thumbnails, test: Thumbnails, threshold: float = DEFAULT_THRESHOLD) -> LeakageReport:
    """The near-duplicates of ``test`` in ``train`` (thumbnails of one size, from :func:`read_thumbnails`)."""
    if threshold < 0:
        raise ConfigError(f"threshold {threshold:g}: must be >= 0 (8-bit levels of mean absolute difference)")
    if train.size != test.size:
        raise ConfigError(
            f"train images were resized to {train.size} px and test images to {test.size} px; read both at one size"
        )
    train_h, train_w = train.image_hw
    test_h, test_w = test.image_hw
    if train_h * test_w != test_h * train_w:
        raise ConfigError(
            f"train images are {size_text((train_h, train_w))} px and test images "
            f"{size_text((test_h, test_w))} px, of different aspects: compare images of one aspect "
            "(set the same image_size in both datasets)"
        )
    nearest, distance = nearest_neighbours(test.pixels_NP, train.pixels_NP)
    return LeakageReport(test.ids, train.ids, nearest, distance * 255, threshold, train.size)


def closest_pairs_picture(
    report: LeakageReport, train: TactileDataset, test: TactileDataset, count: int
) -> torch.Tensor:
    """The ``count`` closest pairs as one image: test images on the top row, their nearest training
    images below, closest pair first, at the test images' size."""

    pairs = report.closest(count)
    tops = torch.stack([test[test_index]["tactile"] for test_index, _, _ in pairs])
    bottoms = torch.stack([train[train_index]["tactile"] for _, train_index, _ in pairs])
    return image_grid(torch.cat([tops, resize_images(bottoms, tuple(tops.shape[-2:]))]), columns=len(pairs))


def _quantile_name(quantile: float) -> str:
    return {0.0: "min", 0.5: "median", 1.0: "max"}.get(quantile, f"{quantile:.0%}")


def _dataset_name(dataset: Any) -> str:
    spec = getattr(dataset, "vqtouch_spec", None)
    return f"dataset {spec.config.name!r}" if spec else type(dataset).__name__

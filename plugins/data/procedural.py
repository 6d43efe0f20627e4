"""The embedded default dataset: procedural paired scenes rendered on demand.

Sample ``i`` is a pure function of ``(seed, i)``: an object of the scene library pressed into
the experiment's sensor (tactile image), the camera view of the same region (visual image),
its class label and a short text description.  When the experiment has a ``paired_sensor``, the
same contact is also rendered by that sensor (``tactile_source``): paired touch-to-touch data
with exact ground truth (GelSight -> DIGIT: ``sensor=digit``, ``paired_sensor=gelsight``).  Samples
are rendered lazily and kept in memory as 8-bit images once rendered (``cache``).  Export a
browsable copy with ``vqtouch data render``.

Split groups: none; every sample is its own group.  Sample ``i`` draws its class, object shape,
pose, press depth and sensor noise from a generator of its own (:func:`sample_generator`), so no
two samples share a contact, a seed or a pose draw, and holding out samples one by one already
holds out unseen seeds and poses.  Grouping by class would hold out whole classes (labels the
generator never trained on), and a coarser "pose family" would not help: the near-duplicates
that ``vqtouch data leakage`` finds among independent samples (a few percent) are faint presses
at nearby spots, often of different classes.
"""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F

from vqtouch.core import BuildContext, SensorFamily, TactileDataset
from vqtouch.core.image_size import extent_hw, image_hw
from vqtouch.sensors.camera import render_visual
from vqtouch.sensors.objects import CLASS_NAMES, OBJECT_CLASSES, sample_contact

from .procedural_plugin import ProceduralDataConfig


def sample_generator(seed: int, index: int) -> torch.Generator:
    """The generator of sample ``index``: independent of the order samples are drawn in."""
    return torch.Generator().manual_seed((seed * 1_000_003 + index * 7_919 + 17) % (2**63 - 1))


def paired_render_generator(seed: int, index: int) -> torch.Generator:
    """The noise generator of sample ``index``'s paired-sensor image: separate from the sample's own,
    so adding a paired sensor leaves every other entry of the sample unchanged."""
    return torch.Generator().manual_seed(sample_generator(seed, index).initial_seed() ^ 0x5EED_0F7A_1C)


def reframe_indentation(
    indentation_BHW: torch.Tensor, from_mm: float | tuple[float, float], to_mm: float | tuple[float, float]
) -> torch.Tensor:
    """An indentation map (mm) imaged over a ``from_mm`` area, seen by a sensor imaging a centred
    ``to_mm`` area at the same resolution: bilinear resampling, no contact outside the original
    area.  The same physical press, framed by the other sensor's field of view.  An area is a
    square's side or a (rows, columns) extent in mm."""
    (from_rows, from_cols), (to_rows, to_cols) = extent_hw(from_mm), extent_hw(to_mm)
    if (from_rows, from_cols) == (to_rows, to_cols):
        return indentation_BHW
    batch, height, width = indentation_BHW.shape
    # affine_grid's x is the column axis.
    theta = torch.tensor([[to_cols / from_cols, 0.0, 0.0], [0.0, to_rows / from_rows, 0.0]]).expand(batch, 2, 3)
    grid = F.affine_grid(theta, [batch, 1, height, width], align_corners=False)
    return F.grid_sample(indentation_BHW[:, None], grid, mode="bilinear", padding_mode="zeros", align_corners=False)[
        :, 0
    ]


class ProceduralTactileDataset(TactileDataset):
    """Procedural (tactile, visual, label, text) samples for one sensor, and the same contacts
    rendered by a second sensor (``tactile_source``) when one is given."""

    def __init__(self, sensor: Any, config: ProceduralDataConfig, paired_sensor: Any = None) -> None:
        self.sensor = sensor
        self.paired_sensor = paired_sensor
        self.config = config
        self.class_names = list(config.classes) or list(CLASS_NAMES)
        self._classes = [OBJECT_CLASSES[CLASS_NAMES.index(name)] for name in self.class_names]
        self._cache: dict[int, dict[str, Any]] = {}

    def __len__(self) -> int:
        return self.config.num_samples

    def new_scenes(self, count: int, seed_offset: int = 1000) -> ProceduralTactileDataset:
        """``count`` newly drawn scenes of the same sensors, classes and settings, from seed ``seed +
        seed_offset``: sample i is a pure function of (seed, i), so none shares a draw with this dataset's
        samples (e.g. more scenes for ``generator.train.grid_pretrain``, never its held-out ones)."""
        if count < 1:
            raise ValueError(f"new_scenes({count}): draw at least one scene")
        seed = (self.config.seed + seed_offset) % 2**31
        if seed == self.config.seed:
            raise ValueError(f"seed_offset={seed_offset} draws this dataset's own scenes again; use another")
        config = self.config.model_copy(update={"seed": seed, "num_samples": count})
        return ProceduralTactileDataset(self.sensor, config, self.paired_sensor)

    def split_groups(self) -> None:
        """None: every sample is an independent draw, its own group (see the module docstring)."""
        return None

    def rendering_sensor(self) -> Any:
        """The sensor that renders every tactile image (its no-contact render is the exact background)."""
        return self.sensor

    def _check_index(self, index: int) -> int:
        if not -len(self) <= index < len(self):
            raise IndexError(f"sample {index} is out of range for a dataset of {len(self)}")
        return index % len(self)

    def render_batch(self, indices: list[int]) -> dict[str, Any]:
        """Render several samples at once (the sensor runs batched): tensors stacked on dim 0."""
        indices = [self._check_index(i) for i in indices]
        extent_mm = self.sensor.imaged_extent_mm(*image_hw(self.config.image_size))
        contacts, visuals, generators = [], [], []
        for index in indices:
            generator = sample_generator(self.config.seed, index)
            label = int(torch.randint(0, len(self._classes), (1,), generator=generator))
            object_class = self._classes[label]
            contact = sample_contact(
                object_class, label, generator, self.config.image_size, extent_mm, self.config.depth_mm
            )
            visuals.append(render_visual(object_class, contact, generator, extent_mm))
            contacts.append(contact)
            generators.append(generator)
        with torch.no_grad():
            # One render call per sample with its own generator: a sample's sensor noise must not
            # depend on which batch it was rendered in.
            tactile = torch.cat(
                [self.sensor.render(c.indentation_mm_HW[None], generator=g) for c, g in zip(contacts, generators)]
            )
        batch: dict[str, Any] = {}
        if self.paired_sensor is not None:
            paired_extent_mm = self.paired_sensor.imaged_extent_mm(*image_hw(self.config.image_size))
            with torch.no_grad():
                batch["tactile_source"] = torch.cat(
                    [
                        self.paired_sensor.render(
                            reframe_indentation(c.indentation_mm_HW[None], extent_mm, paired_extent_mm),
                            generator=paired_render_generator(self.config.seed, index),
                        )
                        for c, index in zip(contacts, indices)
                    ]
                )
            batch["source_sensor"] = [_sensor_id(self.paired_sensor)] * len(indices)
        return batch | {
            "tactile": tactile,
            "visual": torch.stack(visuals),
            "label": torch.tensor([c.class_index for c in contacts]),
            "text": [
                c.description(self.class_names[c.class_index], self._classes[c.class_index].material) for c in contacts
            ],
            "sensor": [_sensor_id(self.sensor)] * len(indices),
            "id": [f"{self.config.seed}-{index:07d}" for index in indices],
            "depth_mm": torch.tensor([c.depth_mm for c in contacts]),
        }

    def __getitem__(self, index: int) -> dict[str, Any]:
        index = self._check_index(index)
        if index in self._cache:
            stored = self._cache[index]
            return {**stored, **{key: stored[key].float() / 255 for key in _IMAGE_KEYS if key in stored}}
        batch = self.render_batch([index])
        sample = {key: value[0] for key, value in batch.items()}
        sample["label"] = int(sample["label"])
        sample["depth_mm"] = float(sample["depth_mm"])
        if self.config.cache:
            self._cache[index] = {
                **sample,
                **{key: (sample[key] * 255).round().to(torch.uint8) for key in _IMAGE_KEYS if key in sample},
            }
            return self[index]
        return sample


#: The image entries of a sample (kept in memory as 8-bit images when cached).
_IMAGE_KEYS = ("tactile", "visual", "tactile_source")


def _sensor_id(sensor: Any) -> str:
    """The id a sample records for the sensor that rendered it."""
    spec = getattr(sensor, "vqtouch_spec", None)
    return sensor.sensor_id or (spec.config.name if spec else type(sensor).__name__)


def build_procedural(
    config: ProceduralDataConfig, context: BuildContext, sensor: SensorFamily, paired_sensor: SensorFamily | None = None
) -> ProceduralTactileDataset:
    """Factory: the scenes rendered by ``sensor``, which the assembly supplies (the experiment's
    sensor, or its target sensor where a stage asks for that), and by ``paired_sensor`` (the
    experiment's paired sensor, when it has one) as each sample's ``tactile_source``."""
    if config.image_size is None:
        config = config.model_copy(update={"image_size": context.image_size})
    return ProceduralTactileDataset(sensor, config, paired_sensor)

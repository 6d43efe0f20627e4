"""The embedded default dataset: procedural paired scenes rendered on demand.

Sample ``i`` is a pure function of ``(seed, i)``: an object of the scene library pressed into
the experiment's sensor (tactile image), the camera view of the same region (visual image),
its class label and a short text description.  Samples are rendered lazily and kept in
memory as 8-bit images once rendered (``cache``).  Export a browsable copy with
``vqtouch data render``.
"""

from __future__ import annotations

from typing import Any, Literal

import torch
from pydantic import Field, field_validator

from vqtouch.core import BuildContext, PluginConfig, SensorFamily, TactileDataset, hookimpl
from vqtouch.sensors.camera import render_visual
from vqtouch.sensors.objects import CLASS_NAMES, OBJECT_CLASSES, sample_contact


class ProceduralDataConfig(PluginConfig):
    """Options of the ``procedural`` dataset (the embedded default data)."""

    name: Literal["procedural"] = "procedural"
    num_samples: int = Field(1000, ge=1, le=10_000_000, description="Number of samples in the dataset.")
    image_size: int | None = Field(None, ge=16, le=1024,
                                   description="Side of the square tactile and visual images; null uses the "
                                               "experiment's data.image_size.")
    seed: int = Field(0, ge=0, le=2**31 - 1, description="Seed; sample i depends only on (seed, i).")
    classes: list[str] = Field(default_factory=list,
                               description=f"Object classes to draw (empty: all). Known: {', '.join(CLASS_NAMES)}.")
    depth_mm: tuple[float, float] = Field((0.2, 1.0), description="Range of press depths in mm.")
    cache: bool = Field(True, description="Keep rendered samples in memory (as 8-bit images).")

    @field_validator("classes")
    @classmethod
    def _known_classes(cls, classes: list[str]) -> list[str]:
        unknown = [name for name in classes if name not in CLASS_NAMES]
        if unknown:
            raise ValueError(f"unknown object classes {unknown}; known: {', '.join(CLASS_NAMES)}")
        if len(set(classes)) != len(classes):
            raise ValueError("object classes are listed twice")
        return classes

    @field_validator("depth_mm")
    @classmethod
    def _depth_range(cls, depth: tuple[float, float]) -> tuple[float, float]:
        if not 0 < depth[0] <= depth[1] <= 5:
            raise ValueError(f"depth_mm must satisfy 0 < low <= high <= 5 mm, got {depth}")
        return depth


def sample_generator(seed: int, index: int) -> torch.Generator:
    """The generator of sample ``index``: independent of the order samples are drawn in."""
    return torch.Generator().manual_seed((seed * 1_000_003 + index * 7_919 + 17) % (2**63 - 1))


class ProceduralTactileDataset(TactileDataset):
    """Procedural (tactile, visual, label, text) samples for one sensor."""

    def __init__(self, sensor: Any, config: ProceduralDataConfig) -> None:
        self.sensor = sensor
        self.config = config
        self.class_names = list(config.classes) or list(CLASS_NAMES)
        self._classes = [OBJECT_CLASSES[CLASS_NAMES.index(name)] for name in self.class_names]
        self._cache: dict[int, dict[str, Any]] = {}

    def __len__(self) -> int:
        return self.config.num_samples

    def _check_index(self, index: int) -> int:
        if not -len(self) <= index < len(self):
            raise IndexError(f"sample {index} is out of range for a dataset of {len(self)}")
        return index % len(self)

    def render_batch(self, indices: list[int]) -> dict[str, Any]:
        """Render several samples at once (the sensor runs batched): tensors stacked on dim 0."""
        indices = [self._check_index(i) for i in indices]
        contacts, visuals, generators = [], [], []
        for index in indices:
            generator = sample_generator(self.config.seed, index)
            label = int(torch.randint(0, len(self._classes), (1,), generator=generator))
            object_class = self._classes[label]
            contact = sample_contact(object_class, label, generator, self.config.image_size,
                                     self.sensor.field_of_view_mm, self.config.depth_mm)
            visuals.append(render_visual(object_class, contact, generator, self.sensor.field_of_view_mm))
            contacts.append(contact)
            generators.append(generator)
        with torch.no_grad():
            # One render call per sample with its own generator: a sample's sensor noise must not
            # depend on which batch it was rendered in.
            tactile = torch.cat([self.sensor.render(c.indentation_mm_HW[None], generator=g)
                                 for c, g in zip(contacts, generators)])
        spec = getattr(self.sensor, "vqtouch_spec", None)
        sensor_id = self.sensor.sensor_id or (spec.config.name if spec else type(self.sensor).__name__)
        return {
            "tactile": tactile, "visual": torch.stack(visuals),
            "label": torch.tensor([c.class_index for c in contacts]),
            "text": [c.description(self.class_names[c.class_index], self._classes[c.class_index].material)
                     for c in contacts],
            "sensor": [sensor_id] * len(indices),
            "id": [f"{self.config.seed}-{index:07d}" for index in indices],
            "depth_mm": torch.tensor([c.depth_mm for c in contacts]),
        }

    def __getitem__(self, index: int) -> dict[str, Any]:
        index = self._check_index(index)
        if index in self._cache:
            stored = self._cache[index]
            return {**stored, "tactile": stored["tactile"].float() / 255, "visual": stored["visual"].float() / 255}
        batch = self.render_batch([index])
        sample = {key: value[0] for key, value in batch.items()}
        sample["label"] = int(sample["label"])
        sample["depth_mm"] = float(sample["depth_mm"])
        if self.config.cache:
            self._cache[index] = {**sample, "tactile": (sample["tactile"] * 255).round().to(torch.uint8),
                                  "visual": (sample["visual"] * 255).round().to(torch.uint8)}
            return self[index]
        return sample


def build_procedural(config: ProceduralDataConfig, context: BuildContext,
                     sensor: SensorFamily) -> ProceduralTactileDataset:
    """Factory: the scenes rendered by ``sensor``, which the assembly supplies (the experiment's
    sensor, or its target sensor where a stage asks for that)."""
    if config.image_size is None:
        config = config.model_copy(update={"image_size": context.image_size})
    return ProceduralTactileDataset(sensor, config)


@hookimpl
def vqtouch_register_datasets(register):
    register("procedural", build_procedural, ProceduralDataConfig, inputs=("sensor",), demo={"num_samples": 240},
             description="Embedded procedural scenes: 12 object classes x any sensor family (tactile, visual, "
                         "label, text).")

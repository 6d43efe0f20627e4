"""Training a generator over a tokenizer's codes, with one condition per step.

:class:`GeneratorTask` is a :class:`vqtouch.plugins.training.trainer.TrainingTask`: the trainer owns the
optimisation, checkpoints, exact resume, EMA, bf16 and data parallelism, as for the tokenizer.
Each step picks one of the experiment's conditioners (the paper's unified training: one
condition per step), encodes the batch's conditions with it, replaces a random
``condition_dropout`` share of them by the conditioner's learned null tokens (what
classifier-free guidance contrasts with), and optimises the generator's loss.

The data are the cached codes of every sample plus the entries of each sample that the
conditioners read (:class:`CodesDataset`): the tokenizer's encoder never runs during training.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import nn

from vqtouch.core import ConditionTokens, Conditioner, Generator, TactileDataset
from vqtouch.plugins.utils.splits import dataset_groups
from vqtouch.plugins.utils.progress import progress

from .stage_plugin import GeneratorTrainConfig  # noqa: F401 - re-exported


class CodesDataset(TactileDataset):
    """Cached codes (N, h, w) with the sample entries the conditioners read, held in memory.

    ``samples[key]`` holds every sample's value of ``key`` (tensors stacked, numbers as a
    tensor, strings as a list); a sample is ``{"codes": codes[i], key: value, ...}``.
    """

    def __init__(
        self,
        codes_NHW: torch.Tensor,
        entries: dict[str, Any],
        class_names: Sequence[str] = (),
        groups: Sequence[str] | None = None,
        split_unit: str = TactileDataset.split_unit,
    ) -> None:
        self.codes_NHW = codes_NHW
        self.entries = entries
        self.class_names = list(class_names)
        # The source dataset's split groups: the generator's held-out split keeps a recording's
        # frames together exactly as the tokenizer's does (the same split of the same samples).
        self.groups = list(groups) if groups is not None else None
        self.split_unit = split_unit
        for key, values in entries.items():
            if len(values) != len(codes_NHW):
                raise ValueError(f"{len(values)} values of {key!r} for {len(codes_NHW)} code grids")
        if self.groups is not None and len(self.groups) != len(codes_NHW):
            raise ValueError(f"{len(self.groups)} split groups for {len(codes_NHW)} code grids")

    @classmethod
    def collect(
        cls, codes_NHW: torch.Tensor, dataset: Any, keys: Sequence[str], desc: str = "reading conditions"
    ) -> CodesDataset:
        """Read ``keys`` of every sample of ``dataset`` (one pass) next to its codes."""
        values: dict[str, list[Any]] = {key: [] for key in keys}
        for index in progress(range(len(dataset)), desc=desc, unit="sample"):
            sample = dataset[index]
            for key in keys:
                if key not in sample:
                    raise KeyError(
                        f"the dataset's samples have no {key!r} (keys: {', '.join(sorted(sample))}); a "
                        f"conditioner reads it: use a dataset that provides it"
                    )
                values[key].append(sample[key])
        entries = {key: _stack(items) for key, items in values.items()}
        return cls(
            codes_NHW,
            entries,
            getattr(dataset, "class_names", []),
            dataset_groups(dataset),
            getattr(dataset, "split_unit", TactileDataset.split_unit),
        )

    def split_groups(self) -> list[str] | None:
        """The source dataset's split groups (None: every sample is its own)."""
        return self.groups

    def __len__(self) -> int:
        return len(self.codes_NHW)

    def __getitem__(self, index: int) -> dict[str, Any]:
        return {"codes": self.codes_NHW[index], **{key: values[index] for key, values in self.entries.items()}}


def _stack(items: list[Any]) -> Any:
    if items and isinstance(items[0], torch.Tensor):
        return torch.stack(items)
    if items and isinstance(items[0], (int, float)) and not isinstance(items[0], bool):
        return torch.tensor(items)
    return items


#: The sample entry holding each sample's contact cells on the code grid (bool (H, W),
#: :func:`.codes.contact_cells`), there when the generator's ``contact_weight`` asks for them.
CONTACT_KEY = "contact_cells"

#: The checkpoint module name of a generator's sensor tag (``sensor_tag.safetensors``).
SENSOR_TAG_MODULE = "sensor_tag"


def absent_key(sample_key: str) -> str:
    """The sample entry that marks a sample lacking the condition ``sample_key`` (a few-shot image of
    an unseen sensor has no visual image): True rows train with the null condition, whatever value
    stands in for the condition."""
    return f"absent:{sample_key}"


def add_sensor_offset(condition: ConditionTokens, sensor_tag: Conditioner, sensors_B: Any) -> ConditionTokens:
    """``condition`` with each row's tokens offset by its sensor's (``sensor_tag``, the ``sensor``
    conditioner), null rows too: the tag says which sensor to draw, the condition what to draw."""
    offset_B1D = sensor_tag.encode(torch.as_tensor(sensors_B, device=condition.tokens_BND.device))
    return ConditionTokens(
        condition.tokens_BND + offset_B1D.to(condition.tokens_BND), condition.is_null_B, condition.grid_BDhw
    )


class SensorTaggedConditioner(nn.Module):
    """A conditioner that draws one sensor of a sensor-tagged generator: its condition and its null
    condition carry that sensor's offset.  Everything else (its sample key, how it parses a condition)
    is the wrapped conditioner's, so samplers and pipelines use it unchanged."""

    def __init__(self, conditioner: Conditioner, sensor_tag: Conditioner, sensor: int) -> None:
        super().__init__()
        if not 0 <= sensor < sensor_tag.num_sensors:
            raise ValueError(f"sensor {sensor} is outside the tag's {sensor_tag.num_sensors} sensors")
        self.conditioner = conditioner
        self.sensor_tag = sensor_tag
        self.sensor = sensor

    def __getattr__(self, name: str) -> Any:
        try:
            return super().__getattr__(name)
        except AttributeError:
            return getattr(self.conditioner, name)

    def _sensors(self, batch_size: int) -> torch.Tensor:
        return torch.full((batch_size,), self.sensor, dtype=torch.long)

    def forward(self, condition: Any, drop_mask_B: torch.Tensor | None = None) -> ConditionTokens:
        tokens = self.conditioner(condition, drop_mask_B)
        return add_sensor_offset(tokens, self.sensor_tag, self._sensors(len(tokens.is_null_B)))

    def null(self, batch_size: int) -> ConditionTokens:
        return add_sensor_offset(self.conditioner.null(batch_size), self.sensor_tag, self._sensors(batch_size))


class GeneratorTask:
    """The generator objective as a :class:`~vqtouch.plugins.training.trainer.TrainingTask` (see the module
    docstring)."""

    def __init__(
        self,
        generator: Generator,
        conditioners: Sequence[Conditioner],
        condition_dropout: float,
        seed: int,
        conditioner_weights: Sequence[float] | None = None,
        sensor_tag: Conditioner | None = None,
    ) -> None:
        if not conditioners:
            raise ValueError("the generator needs at least one conditioner (generator.conditioners)")
        if conditioner_weights is not None and len(conditioner_weights) != len(conditioners):
            raise ValueError(
                f"{len(conditioner_weights)} conditioner weights for {len(conditioners)} conditioners; "
                "give generator.train.conditioner_weights one weight per conditioner"
            )
        self.weights = None if conditioner_weights is None else torch.tensor(conditioner_weights, dtype=torch.float64)
        self.generator = generator
        self.conditioners = list(conditioners)
        self.condition_dropout = condition_dropout
        self.seed = seed
        self.modules: dict[str, nn.Module] = {"generator": generator}
        for index, conditioner in enumerate(self.conditioners):
            self.modules[f"conditioner_{index}"] = conditioner
        # A sensor tag (generator.sensor_tag) offsets every condition by its row's sensor_index.
        self.sensor_tag = sensor_tag
        if sensor_tag is not None:
            self.modules[SENSOR_TAG_MODULE] = sensor_tag

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        """One optimizer over the generator and every trainable conditioner parameter."""
        params = [p for module in self.modules.values() for p in module.parameters() if p.requires_grad]
        return {"generator": params}

    def pick(self, step: int) -> int:
        """The conditioner of ``step``: a pure function of (seed, step), so a resumed run picks the same."""
        if len(self.conditioners) == 1:
            return 0
        chooser = torch.Generator().manual_seed(self.seed * 1_000_003 + step)
        if self.weights is None:
            return int(torch.randint(len(self.conditioners), (1,), generator=chooser))
        return int(torch.multinomial(self.weights, 1, generator=chooser))

    def condition_tokens(self, index: int, batch: dict[str, Any], drop_B: torch.Tensor | None) -> Any:
        """The tokens of conditioner ``index`` for ``batch`` (rows in ``drop_B`` get its null tokens, as do
        rows that lack the condition: ``batch[absent_key(KEY)]`` True), offset by each row's sensor when
        the generator has a sensor tag."""
        conditioner = self.conditioners[index]
        absent_B = batch.get(absent_key(conditioner.sample_key))
        if absent_B is not None:
            absent_B = absent_B.to(device=batch["codes"].device, dtype=torch.bool)
            drop_B = absent_B if drop_B is None else drop_B | absent_B
        condition = conditioner(conditioner.condition_of(batch), drop_B)
        if self.sensor_tag is None:
            return condition
        return add_sensor_offset(condition, self.sensor_tag, batch[self.sensor_tag.sample_key])

    def training_step(self, batch: dict[str, Any], step: int, trainer: Any) -> dict[str, float]:
        """One step with one conditioner, its conditions dropped to null at the configured rate."""
        for module in self.modules.values():
            module.train()
        index = self.pick(step)
        codes_BHW = batch["codes"]
        drop_B = torch.rand(len(codes_BHW), device=codes_BHW.device) < self.condition_dropout
        # Only a generator that asked for the contact cells (vq_diffusion's contact_weight) gets them.
        contact = {} if CONTACT_KEY not in batch else {"contact_BHW": batch[CONTACT_KEY]}
        with trainer.autocast():
            condition = self.condition_tokens(index, batch, drop_B)
            loss, scalars = self.generator.training_loss(codes_BHW, condition, **contact)
        trainer.optimize("generator", loss)
        return {"loss": float(loss.detach()), **scalars, "conditioner": float(index)}

    @torch.no_grad()
    def validation_loss(self, batch: dict[str, Any], trainer: Any) -> torch.Tensor:
        """(B,) held-out loss with every conditioner in turn (averaged), in eval mode with a fixed
        generator, so checkpoints are compared on the same draws."""
        for module in self.modules.values():
            module.eval()
        codes_BHW = batch["codes"]
        total = torch.zeros((), device=codes_BHW.device)
        for index in range(len(self.conditioners)):
            draws = torch.Generator(device=codes_BHW.device).manual_seed(self.seed + 17 * index)
            with trainer.autocast():
                condition = self.condition_tokens(index, batch, None)
                loss, _ = self.generator.training_loss(codes_BHW, condition, generator=draws)
            total = total + loss.float()
        return (total / len(self.conditioners)).expand(len(codes_BHW))

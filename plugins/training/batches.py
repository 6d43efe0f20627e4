"""The data order of a training run: a pure function of (seed, epoch), so a resumed run sees the
batches an uninterrupted one would, and each process takes its share of every batch."""

from __future__ import annotations

import functools

from collections.abc import Iterator
from typing import Any

import torch


def collate_samples(samples: list[dict[str, Any]]) -> dict[str, Any]:
    """Stack tensors and numbers of dataset samples; keep strings as lists."""
    batch: dict[str, Any] = {}
    for key in samples[0]:
        values = [sample[key] for sample in samples]
        if isinstance(values[0], torch.Tensor):
            batch[key] = torch.stack(values)
        elif isinstance(values[0], (int, float)):
            batch[key] = torch.tensor(values)
        else:
            batch[key] = values
    return batch


@functools.lru_cache(maxsize=4)
def epoch_order(seed: int, epoch: int, size: int) -> tuple[int, ...]:
    """The sample order of one epoch: a pure function of (seed, epoch) (cached: every step of an
    epoch asks for it)."""
    return tuple(torch.randperm(size, generator=torch.Generator().manual_seed(seed * 100_003 + epoch)).tolist())


def batch_indices(seed: int, step: int, batch_size: int, size: int, rank: int = 0, world: int = 1) -> list[int]:
    """This process's share of the global batch of ``step`` (global batch = batch_size * world)."""
    global_batch = batch_size * world
    per_epoch = max(1, size // global_batch)
    epoch, position = divmod(step, per_epoch)
    order = epoch_order(seed, epoch, size)
    start = position * global_batch
    return list(order[start : start + global_batch][rank::world])


class StepBatches:
    """The batch indices of steps ``start`` to ``stop``, made one at a time (a list of every batch of
    a long run would not fit in memory)."""

    def __init__(self, seed: int, start: int, stop: int, batch_size: int, size: int, rank: int, world: int) -> None:
        self.seed, self.start, self.stop = seed, start, stop
        self.batch_size, self.size, self.rank, self.world = batch_size, size, rank, world

    def __len__(self) -> int:
        return max(0, self.stop - self.start)

    def __iter__(self) -> Iterator[list[int]]:
        for step in range(self.start, self.stop):
            yield batch_indices(self.seed, step, self.batch_size, self.size, self.rank, self.world)

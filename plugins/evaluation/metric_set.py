"""Named metrics scored together, skipped ones reported as skipped."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

import torch

from vqtouch.core.components import Metric


class MetricSet:
    """Named metrics scored together: the one place that reports skipped metrics as skipped.

    ``update`` feeds every available metric; :meth:`scores` returns ``{prefix + name: value}`` for
    those and, when any is skipped, ``{"skipped": {name: reason}}`` (a skipped metric never gets
    a number).
    """

    def __init__(self, metrics: Mapping[str, Metric] | Iterable[tuple[str, Metric]]) -> None:
        self.metrics: dict[str, Metric] = dict(metrics)

    def __len__(self) -> int:
        return len(self.metrics)

    def available(self) -> dict[str, Metric]:
        """The metrics that can be computed here, by name."""
        return {name: metric for name, metric in self.metrics.items() if metric.skipped is None}

    def skipped(self) -> dict[str, str]:
        """Why each skipped metric is skipped, by name."""
        return {name: metric.skipped for name, metric in self.metrics.items() if metric.skipped is not None}

    def reset(self) -> None:
        """Forget everything every metric has seen."""
        for metric in self.available().values():
            metric.reset()

    def update(self, predicted_B3HW: torch.Tensor, target_B3HW: torch.Tensor) -> None:
        """Add a batch of image pairs (in [0, 1]) to every available metric."""
        for metric in self.available().values():
            metric.update(predicted_B3HW, target_B3HW)

    def scores(self, prefix: str = "", digits: int | None = 4) -> dict[str, Any]:
        """Each available metric's value as ``prefix + name`` (rounded to ``digits`` unless None), and
        ``"skipped"``: ``{name: reason}`` when a metric is skipped."""
        values: dict[str, Any] = {}
        for name, metric in self.available().items():
            value = float(metric.compute())
            values[prefix + name] = round(value, digits) if digits is not None else value
        if self.skipped():
            values["skipped"] = self.skipped()
        return values

    def score(
        self, predicted_B3HW: torch.Tensor, target_B3HW: torch.Tensor, prefix: str = "", digits: int | None = 4
    ) -> dict[str, Any]:
        """:meth:`reset`, one :meth:`update` with these pairs, then :meth:`scores`."""
        self.reset()
        self.update(predicted_B3HW, target_B3HW)
        return self.scores(prefix, digits)

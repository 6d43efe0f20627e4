"""Contracts every registered plugin must meet, parametrized over the live registries."""

import pytest
from pydantic import BaseModel

from vqtouch.core import BuildContext, Metric, load_plugins
from vqtouch.core.config import ExperimentConfig

HOST = load_plugins(autoload=False)
ENTRIES = [(entry.kind, entry.name) for entry in HOST.entries()]


@pytest.mark.parametrize("kind, name", ENTRIES)
def test_config_model_is_strict_frozen_and_documented(kind, name):
    model = HOST.registry(kind).get(name).config_model
    assert model.model_config.get("extra") == "forbid"
    assert model.model_config.get("frozen") is True
    assert model.__doc__ and model.__doc__.strip()
    undocumented = [field for field, info in model.model_fields.items() if not info.description]
    assert not undocumented, f"{kind} {name!r}: fields without description: {undocumented}"
    assert model().name == name  # every option has a default, so `--set slot.name=X` alone works


@pytest.mark.parametrize("kind, name", ENTRIES)
def test_entry_has_description_and_versioned_source(kind, name):
    entry = HOST.registry(kind).get(name)
    assert entry.description
    assert entry.source.distribution == "vqtouch" and entry.source.version


@pytest.mark.parametrize("name", HOST.registry("metric").names())
def test_every_metric_prefers_identical_images(name):
    import torch

    metric = HOST.build("metric", name, BuildContext())
    assert isinstance(metric, Metric)
    target = torch.rand(2, 3, 32, 32, generator=torch.Generator().manual_seed(0))
    noisy = (target + 0.2 * torch.randn(target.shape, generator=torch.Generator().manual_seed(1))).clamp(0, 1)
    metric.update(target, target)
    same = metric.compute()
    metric.reset()
    metric.update(noisy, target)
    assert (same > metric.compute()) == metric.higher_is_better


def _section_models(model: type[BaseModel]):
    yield model
    for info in model.model_fields.values():
        annotation = info.annotation
        if isinstance(annotation, type) and issubclass(annotation, BaseModel):
            yield from _section_models(annotation)


def test_experiment_config_fields_are_documented():
    for model in _section_models(ExperimentConfig):
        assert model.__doc__, model
        undocumented = [field for field, info in model.model_fields.items() if not info.description]
        assert not undocumented, f"{model.__name__}: {undocumented}"

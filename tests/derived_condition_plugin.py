"""A third-party conditioner of a *derived* condition, importable as ``derived_condition_plugin``
(load it with ``VQTOUCH_PLUGINS=derived_condition_plugin``): ``material`` is not an entry of any
sample; it is computed from each sample's class label through the class names the build context
carries, and ``vqtouch generate --condition material=NAME`` gives it directly."""

from __future__ import annotations

from typing import Any, Literal

import torch
from torch import nn

from vqtouch.core import BuildContext, Conditioner, ConfigError, PluginConfig, hookimpl

MATERIALS = ("rigid", "soft", "textured")


def material_of(class_name: str) -> str:
    """The (made-up) material of a class: a fixed function of its name."""
    return MATERIALS[len(class_name) % len(MATERIALS)]


class MaterialConfig(PluginConfig):
    """Options of the ``material`` conditioner (none besides its name)."""

    name: Literal["material"] = "material"


class MaterialConditioner(Conditioner):
    """One learned token per material; the material of a training sample comes from its label."""

    sample_key = "material"
    derived_from = ("label",)

    def __init__(self, cond_dim: int, class_names: tuple[str, ...]) -> None:
        super().__init__(cond_dim, 1)
        self.class_names = class_names
        self.embedding = nn.Embedding(len(MATERIALS), cond_dim)

    def derive(self, batch: dict[str, Any]) -> torch.Tensor:
        labels = batch["label"].tolist()
        return torch.tensor(
            [MATERIALS.index(material_of(self.class_names[label])) for label in labels], device=batch["label"].device
        )

    def parse_condition(self, value: Any, **_: Any) -> int:
        if str(value) not in MATERIALS:
            raise ConfigError(f"--condition material={value}: choose one of {', '.join(MATERIALS)}")
        return MATERIALS.index(str(value))

    def encode(self, condition: torch.Tensor) -> torch.Tensor:
        return self.embedding(condition.long().to(self.embedding.weight.device)).unsqueeze(1)


def build_material(config: MaterialConfig, context: BuildContext) -> MaterialConditioner:
    if not context.class_names:
        raise ConfigError("conditioner 'material' derives from class names; use a labelled dataset")
    return MaterialConditioner(context.cond_dim, context.class_names)


@hookimpl
def vqtouch_register_conditioners(register):
    register("material", build_material, MaterialConfig, description="A material derived from the class label.")

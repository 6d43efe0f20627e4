"""Strict pydantic models: the base of every plugin's options and every config section.

Each plugin owns a strict options model (unknown keys are errors that list the allowed
ones, fields are documented and bounded); the experiment config only composes them.  The
``name`` field is the discriminator: a plugin registered as ``"label"`` declares
``name: Literal["label"] = "label"``.
"""

from __future__ import annotations

import typing
from collections.abc import Mapping
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, model_validator
from pydantic_core import PydanticCustomError

from .errors import closest_match


class StrictModel(BaseModel):
    """Frozen model that rejects unknown keys, naming the allowed ones and the closest match."""

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True)

    @model_validator(mode="before")
    @classmethod
    def _reject_unknown_keys(cls, data: Any) -> Any:
        if isinstance(data, Mapping):
            allowed = set(cls.model_fields)
            for key in data:
                if key not in allowed:
                    hint = closest_match(str(key), allowed)
                    raise PydanticCustomError(
                        "unknown_option",
                        "unknown option {key}; allowed: {allowed}{hint}",
                        {
                            "key": repr(key),
                            "allowed": ", ".join(sorted(allowed)),
                            "hint": f"; did you mean {hint!r}?" if hint else "",
                        },
                    )
        return data


class PluginConfig(StrictModel):
    """Options of one plugin instance; subclass it and narrow ``name`` to a ``Literal``."""

    name: str = Field(description="Registered name of the plugin that this block configures.")

    @classmethod
    def __pydantic_init_subclass__(cls, **kwargs: Any) -> None:
        # Subclasses narrow `name` to a Literal, which drops the inherited description.
        super().__pydantic_init_subclass__(**kwargs)
        field = cls.model_fields.get("name")
        if field is not None and not field.description:
            field.description = f"Plugin name; {literal_name_of(cls)!r} selects this plugin."
            cls.model_rebuild(force=True)


def literal_name_of(config_model: type[PluginConfig]) -> str | None:
    """Return the single string of the model's ``name: Literal[...]`` annotation, if it has one."""
    field = config_model.model_fields.get("name")
    if field is None or typing.get_origin(field.annotation) is not typing.Literal:
        return None
    values = typing.get_args(field.annotation)
    return values[0] if len(values) == 1 and isinstance(values[0], str) else None

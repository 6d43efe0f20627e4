"""The files vqtouch reads back (cluster.json, report.json, fewshot.json, adapt.json, products.json,
dataset index rows): parsed and validated, so that a damaged or hand-edited file is one line naming
the file and the field, never a traceback from deep inside a reader.

Each reader declares what it needs of a file as a pydantic model (:class:`FileModel`: strict types,
no NaN or infinity, unknown fields kept), and reads it with :func:`read_model`.  Paths a file names
(a run's products) are resolved with :func:`inside_root`, which refuses one that leaves the folder
the file describes.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, TypeVar

from pydantic import BaseModel, ConfigDict, ValidationError

from vqtouch.core.errors import ConfigError


class FileModel(BaseModel):
    """What a reader needs of a JSON file: strict types (``"3"`` is not 3), finite numbers only
    (``"NaN"``, ``NaN`` and the infinities are refused), other fields kept as they are."""

    model_config = ConfigDict(strict=True, allow_inf_nan=False, extra="allow")


Model = TypeVar("Model", bound=BaseModel)


def read_json(path: str | Path) -> Any:
    """``path`` parsed as JSON; ConfigError naming it when it is unreadable or not JSON."""
    path = Path(path)
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f"{path}: not valid JSON ({exc}); restore it or make it again") from None


def validation_message(exc: ValidationError) -> str:
    """The first problem of a pydantic error as ``field: what is wrong (got value)``."""
    error = exc.errors()[0]
    where = ".".join(str(part) for part in error["loc"])
    got = f" (got {error['input']!r})" if "input" in error and not isinstance(error["input"], (dict, list)) else ""
    text = error["msg"][:1].lower() + error["msg"][1:]
    return f"{where}: {text}{got}" if where else f"{text}{got}"


def check_model(data: Any, model: type[Model], source: str | Path) -> Model:
    """``data`` validated by ``model``; ConfigError naming ``source`` and the first bad field."""
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(f"{source}: {validation_message(exc)}; make the file again, or fix that field") from None


def read_model(path: str | Path, model: type[Model]) -> Model:
    """The JSON file ``path`` validated by ``model`` (see :func:`check_model`)."""
    return check_model(read_json(path), model, path)


def inside_root(relative: str, root: Path, source: str | Path) -> Path:
    """``root / relative`` resolved, refused in one line (ConfigError naming ``source``) when it leaves
    ``root``: ``../``, an absolute path, a link out."""
    path = (root / relative).resolve()
    if not path.is_relative_to(root.resolve()):
        raise ConfigError(f"{source}: {relative!r} is outside {root}; a file may name only paths inside its folder")
    return path

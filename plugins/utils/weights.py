"""Finding pretrained weight files on disk.  Nothing is ever downloaded.

Components that need pretrained weights (CLIP, LPIPS backbones, Inception for FID) call
:func:`resolve_weights`.  The first hit wins:

1. an explicit path (CLI flag or config key);
2. the component's own environment variable (e.g. ``VQTOUCH_CLIP_CKPT``);
3. ``VQTOUCH_WEIGHTS_DIR`` searched for the file's original name.

A missing file raises :class:`MissingWeightsError` naming the file, the three ways to
provide it, and where it can be downloaded on a connected machine.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

from vqtouch.core.errors import MissingWeightsError

ENV_WEIGHTS_DIR = "VQTOUCH_WEIGHTS_DIR"


@dataclass(frozen=True)
class WeightsSpec:
    """A pretrained file a component can use: its usual name, variable and origin."""

    description: str
    filenames: tuple[str, ...]
    env_var: str
    config_hint: str
    source_url: str = ""
    sha256_prefix: str = ""


def resolve_weights(spec: WeightsSpec, explicit: str | os.PathLike[str] | None = None) -> Path:
    """Return the path of ``spec``'s weights file or raise :class:`MissingWeightsError`."""
    if explicit:
        path = Path(explicit).expanduser()
        if not path.is_file():
            raise MissingWeightsError(
                f"{spec.description}: file {str(path)!r} (from {spec.config_hint}) does not exist"
            )
        return _checked(spec, path)
    from_env = os.environ.get(spec.env_var, "").strip()
    if from_env:
        path = Path(from_env).expanduser()
        if not path.is_file():
            raise MissingWeightsError(f"{spec.description}: {spec.env_var}={from_env!r} is not a file")
        return _checked(spec, path)
    weights_dir = os.environ.get(ENV_WEIGHTS_DIR, "").strip()
    if weights_dir:
        for filename in spec.filenames:
            candidate = Path(weights_dir).expanduser() / filename
            if candidate.is_file():
                return _checked(spec, candidate)
    names = " or ".join(spec.filenames) if spec.filenames else "the weights file"
    where = f" (download it on a connected machine from {spec.source_url})" if spec.source_url else ""
    raise MissingWeightsError(
        f"{spec.description} needs {names}{where}; provide it with {spec.config_hint}, "
        f"the environment variable {spec.env_var}=PATH, or put it in the folder named by {ENV_WEIGHTS_DIR}. "
        "vqtouch never downloads weights and never substitutes random ones"
    )


def _checked(spec: WeightsSpec, path: Path) -> Path:
    if spec.sha256_prefix:
        digest = sha256_of(path)
        if not digest.startswith(spec.sha256_prefix):
            raise MissingWeightsError(
                f"{spec.description}: {path} has sha256 {digest[:12]}..., expected a digest starting with "
                f"{spec.sha256_prefix}; the file is corrupt or a different model"
            )
    return path


def sha256_of(path: str | os.PathLike[str], chunk_size: int = 1 << 20) -> str:
    """Hex SHA-256 of a file, read in chunks."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for chunk in iter(lambda: handle.read(chunk_size), b""):
            digest.update(chunk)
    return digest.hexdigest()

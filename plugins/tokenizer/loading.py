"""Loading a trained tokenizer: from a run (its newest good checkpoint, a step, or the best one),
from a checkpoint folder outside any run (what ``vqtouch adapt`` writes) or from a bundle
(``pretrained:NAME``), and the helpers that read its files.  Part of the tokenizer package's
public API (``vqtouch.plugins.tokenizer``): other packages load tokenizers through it, never
through the stage module.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch

from vqtouch.core import ConfigError, PluginHost, load, read_metadata
from vqtouch.plugins.runtime.run_dir import RunDir
from vqtouch.core.checkpoint import files_digest, is_pretrained, open_pretrained

from .training import Tokenizer

#: The files of a tokenizer checkpoint, in every step folder of a run and in an adapted folder.
TOKENIZER_FILES = ("autoencoder.safetensors", "quantizer.safetensors")
#: Beside them in a folder adapted with ``rebase``: :attr:`Tokenizer.rebase_3HW` (tensor ``rebase_3HW``).
REBASE_FILE = "rebase.safetensors"


def tokenizer_paths(folder: str | Path) -> list[Path]:
    """The files that make a tokenizer checkpoint folder what it is: :data:`TOKENIZER_FILES` and, when
    the folder has one, :data:`REBASE_FILE` (what a digest or a code cache must cover)."""
    folder = Path(folder)
    rebase = [folder / REBASE_FILE] if (folder / REBASE_FILE).is_file() else []
    return [folder / name for name in TOKENIZER_FILES] + rebase


def save_rebase(folder: str | Path, rebase_3HW: torch.Tensor, metadata: dict[str, str]) -> None:
    """Write :attr:`Tokenizer.rebase_3HW` into a tokenizer checkpoint folder (see :data:`REBASE_FILE`)."""
    from safetensors.torch import save_file

    save_file({"rebase_3HW": rebase_3HW.detach().float().cpu().contiguous()}, str(Path(folder) / REBASE_FILE), metadata)


def _read_rebase(folder: Path, device: str) -> torch.Tensor | None:
    if not (folder / REBASE_FILE).is_file():
        return None
    from safetensors.torch import load_file

    tensors = load_file(str(folder / REBASE_FILE), device=device)
    if set(tensors) != {"rebase_3HW"} or tensors["rebase_3HW"].ndim != 3 or tensors["rebase_3HW"].shape[0] != 3:
        raise ConfigError(f"{folder / REBASE_FILE}: not a tokenizer's rebase image (one (3, H, W) tensor rebase_3HW)")
    return tensors["rebase_3HW"]


def load_tokenizer(
    run_or_folder: str | Path | RunDir, host: PluginHost, step: int | str | None = None, device: str = "cpu"
) -> tuple[Tokenizer, Path]:
    """Load the autoencoder and quantizer of a run (its newest good checkpoint, ``step``, or with
    ``step="best"`` the one that scored best on the held-out split) or of a checkpoint folder.

    A run's folder comes from :meth:`RunDir.checkpoint`, which refuses files made with another
    config than the run's; so does a ``step-*`` folder given inside a run.  A checkpoint folder
    outside any run (copied elsewhere) is loaded as it is, and ``pretrained:NAME`` loads a bundle's
    tokenizer (its folder is returned: read-only, inside the installed package).
    """
    if is_pretrained(run_or_folder):
        if step is not None:
            raise ConfigError(f"--step chooses within a run; {run_or_folder} is one bundled tokenizer")
        bundle = open_pretrained(str(run_or_folder), host, device, tokenizer_only=True)
        return bundle.tokenizer, bundle.tokenizer_folder
    if isinstance(run_or_folder, RunDir):
        run, path = run_or_folder, run_or_folder.path
    else:
        path = Path(run_or_folder)
        run = None
        if all((path / name).is_file() for name in TOKENIZER_FILES):
            inside = path.parent.parent
            if (
                path.parent.name == "checkpoints"
                and path.name.startswith("step-")
                and path.name[5:].isdigit()
                and (inside / "config.json").is_file()
            ):
                run, step = RunDir.open(inside), int(path.name[5:])
            else:
                folder = path
        else:
            run = RunDir.open(path)
    if run is not None:
        folder = run.checkpoint(host, step, required_files=TOKENIZER_FILES)
    autoencoder = load(folder / TOKENIZER_FILES[0], host=host, map_location=device)
    quantizer = load(folder / TOKENIZER_FILES[1], host=host, map_location=device)
    return Tokenizer(autoencoder, quantizer, _read_rebase(folder, device)).eval(), folder


def tokenizer_location(path: str | Path, host: PluginHost | None = None) -> RunDir | Path:
    """Where a tokenizer lives: the run at ``path``, or ``path`` itself when it is a checkpoint
    folder holding the tokenizer files outside any run (e.g. what ``vqtouch adapt`` writes), or for
    ``pretrained:NAME`` the bundle's tokenizer folder (``host`` opens the bundle)."""
    if is_pretrained(path):
        if host is None:
            raise ConfigError(f"{path}: a bundle is opened through the plugins; pass the plugin host")
        return open_pretrained(str(path), host, tokenizer_only=True).tokenizer_folder
    path = Path(path)
    if not (path / "config.json").is_file() and all((path / name).is_file() for name in TOKENIZER_FILES):
        return path
    return RunDir.open(path)


def tokenizer_digest(folder: str | Path) -> str:
    """The SHA-256 of a tokenizer checkpoint folder's weight files: what a generator or a clustering
    records of the tokenizer it was made with, to refuse a tokenizer retrained or replaced since."""
    return files_digest(tokenizer_paths(folder))


def tokenizer_configs(folder: str | Path) -> tuple[dict[str, Any], dict[str, Any], int]:
    """The autoencoder and quantizer plugin configs and the image size a tokenizer checkpoint
    folder was made with (read from its headers)."""
    headers = [read_metadata(Path(folder) / name) for name in TOKENIZER_FILES]
    image_size = json.loads(headers[0]["vqtouch.context"])["image_size"]
    return json.loads(headers[0]["vqtouch.config"]), json.loads(headers[1]["vqtouch.config"]), image_size


@torch.no_grad()
def reconstruct_all(tokenizer: Tokenizer, images_B3HW: torch.Tensor, batch_size: int = 16) -> torch.Tensor:
    """Reconstructions in [0, 1] of a stack of images in [0, 1], ``batch_size`` at a time."""
    return torch.cat(
        [tokenizer.reconstruct(images_B3HW[i : i + batch_size])[0] for i in range(0, len(images_B3HW), batch_size)]
    )

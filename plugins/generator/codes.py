"""The tokenizer's codes of a whole dataset, computed once and cached as safetensors.

A generator learns over code grids, so its training would otherwise run the tokenizer's
encoder on every batch of every step.  The codes depend only on the tokenizer's weights and on
the images, so they are computed once per (tokenizer checkpoint, dataset config) and kept in
the user cache folder (``$XDG_CACHE_HOME/vqtouch/codes/``, see
:func:`vqtouch.plugins.utils.splits.user_cache_folder`).  The key hashes the tokenizer's weight files
(their tensors and header, not their path: a copied run hits the same entry) and the config that decides
the images (dataset block, image size, sensors).  A cache entry that cannot be read or does
not fit is recomputed with a warning; the cache is only ever a speed-up.

Caveat: a dataset read from files is keyed by its config, not by the files' contents; after
changing the images of a folder in place, pass ``use_cache=False`` (``generator.train.code_cache
=false``) once, or delete the cache folder.
"""

from __future__ import annotations

import hashlib
import json
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from safetensors import safe_open
from safetensors.torch import save_file

from vqtouch.core import atomic_write
from vqtouch.plugins.utils.splits import user_cache_folder
from vqtouch.core.errors import VqtouchWarning
from vqtouch.plugins.utils.progress import progress
from vqtouch.plugins.training.batches import collate_samples

#: Bumped when the cache file's layout changes (older entries are then simply not found).
CACHE_VERSION = "1"


class CodeCacheWarning(VqtouchWarning):
    """A cached code file was unusable and the codes were computed again."""


def weights_digest(paths: Sequence[Path]) -> str:
    """SHA-256 of the weights in the safetensors files ``paths``: every tensor's name, dtype, shape and
    bytes, and the header metadata, in sorted order (so two files holding the same weights match,
    whatever order their writer put the header in)."""
    digest = hashlib.sha256()
    for path in paths:
        with safe_open(str(path), framework="pt") as handle:
            digest.update(json.dumps(sorted((handle.metadata() or {}).items())).encode())
            for name in sorted(handle.keys()):
                tensor = handle.get_tensor(name).contiguous().reshape(-1)  # 0-d tensors cannot be viewed as bytes
                digest.update(f"{name}:{tensor.dtype}:{tuple(tensor.shape)}".encode())
                digest.update(tensor.view(torch.uint8).numpy().tobytes() if tensor.numel() else b"")
    return digest.hexdigest()


def cache_key(tokenizer_files: Sequence[Path], images_config: dict[str, Any]) -> str:
    """The cache entry's name: the tokenizer's weights and the config that decides the images."""
    data = json.dumps(images_config, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(f"{CACHE_VERSION}:{weights_digest(tokenizer_files)}:{data}".encode()).hexdigest()[:32]


@torch.no_grad()
def encode_dataset(
    tokenizer: Any,
    dataset: Any,
    *,
    batch_size: int = 32,
    device: torch.device | str = "cpu",
    desc: str = "encoding codes",
) -> torch.Tensor:
    """Codes (N, h, w) int64 of every sample's tactile image, in dataset order."""
    tokenizer.eval()
    codes = []
    for start in progress(range(0, len(dataset), batch_size), desc=desc, unit="batch"):
        batch = collate_samples([dataset[i] for i in range(start, min(start + batch_size, len(dataset)))])
        codes.append(tokenizer.encode_codes(batch["tactile"].to(device)).cpu().long())
    return torch.cat(codes)


def dataset_codes(
    tokenizer: Any,
    tokenizer_files: Sequence[Path],
    dataset: Any,
    images_config: dict[str, Any],
    *,
    batch_size: int = 32,
    device: torch.device | str = "cpu",
    use_cache: bool = True,
    cache_folder: Path | None = None,
) -> tuple[torch.Tensor, dict[str, Any]]:
    """The codes (N, h, w) of ``dataset`` under ``tokenizer``, from the cache when it holds them.

    Returns the codes and a record of where they came from (``{"cache": "hit"|"miss"|"off",
    "path": ..., "seconds": ...}``), which the generator stage writes into its outputs.
    ``tokenizer_files`` are the tokenizer's weight files (they key the cache).
    """
    import time

    folder = cache_folder if cache_folder is not None else user_cache_folder()
    path = None
    if use_cache and folder is not None:
        path = folder / "codes" / f"{cache_key(tokenizer_files, images_config)}.safetensors"
        cached = _read(path, len(dataset), tokenizer.quantizer.codebook_size)
        if cached is not None:
            return cached, {"cache": "hit", "path": str(path), "seconds": 0.0}
    tic = time.perf_counter()
    codes = encode_dataset(tokenizer, dataset, batch_size=batch_size, device=device)
    seconds = time.perf_counter() - tic
    if path is not None:
        try:
            metadata = {
                "vqtouch.codes_version": CACHE_VERSION,
                "vqtouch.images": json.dumps(images_config, default=str),
                "vqtouch.tokenizer": json.dumps([str(p) for p in tokenizer_files]),
            }
            atomic_write(path, lambda tmp: save_file({"codes": codes.to(torch.int32)}, str(tmp), metadata=metadata))
        except OSError as exc:  # a read-only or full cache folder: the codes are still good
            warnings.warn(
                f"could not cache the codes in {path} ({exc.strerror or exc}); they will be computed again next time",
                CodeCacheWarning,
                stacklevel=2,
            )
            path = None
    return codes, {
        "cache": "miss" if path is not None else "off",
        "path": str(path) if path else None,
        "seconds": round(seconds, 3),
    }


def _read(path: Path, count: int, codebook_size: int) -> torch.Tensor | None:
    """The cached codes at ``path`` if the file is there, readable and fits; None otherwise."""
    if not path.is_file():
        return None
    try:
        with safe_open(str(path), framework="pt") as handle:
            codes = handle.get_tensor("codes").long()
    except Exception as exc:  # noqa: BLE001 - safetensors raises several error types
        warnings.warn(
            f"the code cache {path} is unreadable ({str(exc).splitlines()[0] if str(exc) else exc}); "
            "computing the codes again",
            CodeCacheWarning,
            stacklevel=3,
        )
        return None
    if codes.ndim != 3 or len(codes) != count or (codes.numel() and (codes.min() < 0 or codes.max() >= codebook_size)):
        warnings.warn(
            f"the code cache {path} does not fit this dataset and tokenizer (shape {tuple(codes.shape)}); "
            "computing the codes again",
            CodeCacheWarning,
            stacklevel=3,
        )
        return None
    return codes


@torch.no_grad()
def canonical_background(
    codes_NHW: torch.Tensor,
    tokenizer: Any,
    background_3HW: torch.Tensor,
    *,
    margin: int = 1,
    batch_size: int = 64,
    images_N3HW: torch.Tensor | None = None,
) -> tuple[torch.Tensor, float]:
    """The codes with every cell away from the contact set to the no-contact image's own code there,
    and the share of cells changed.

    Why: the tokenizer's encoder sees the whole image, so identical no-contact patches get different
    (near-synonymous) codes depending on where the contact is; measured on the bundled tokenizer,
    only 30% of the no-contact cells of the tour's images carry the code of the no-contact image,
    while decoding the canonical grid costs 0.2 dB of contact PSNR (docs/generation.md).  A
    generator trained on the raw codes spends its capacity guessing those synonyms; on the
    canonical ones the background is a function of position and its learning goes to the contact.

    A cell is contact when the decoded image differs from ``background_3HW`` there
    (:func:`~vqtouch.plugins.evaluation.contact.contact_mask`, which allows for camera noise), or
    lies within ``margin`` cells of one that does.  Given the encoded images themselves
    (``images_N3HW``), the contact is found on them instead: a tokenizer adapted to another sensor
    decodes the family's codes in a changed appearance, whose contact the mask would miss (measured:
    75% of the family's cells called background under an adapted tokenizer, 35% under its own).
    """
    from vqtouch.plugins.evaluation.contact import contact_mask

    if len(codes_NHW) == 0:
        return codes_NHW, 0.0
    device = tokenizer.device
    background_codes_HW = tokenizer.encode_codes(background_3HW[None].to(device)).cpu()[0]
    if background_codes_HW.shape != codes_NHW.shape[1:]:
        raise ValueError(
            f"the background's code grid {tuple(background_codes_HW.shape)} is not the codes' "
            f"{tuple(codes_NHW.shape[1:])}"
        )
    rows = []
    for start in range(0, len(codes_NHW), batch_size):
        codes_BHW = codes_NHW[start : start + batch_size]
        if images_N3HW is not None:
            seen_B3HW = images_N3HW[start : start + batch_size].float().cpu()
        else:
            seen_B3HW = tokenizer.decode_codes(codes_BHW.to(device)).float().cpu()
        pixels_BHW = contact_mask(seen_B3HW, background_3HW.float().cpu().expand_as(seen_B3HW))
        cells_B1hw = F.adaptive_max_pool2d(pixels_BHW[:, None].float(), tuple(codes_NHW.shape[1:]))
        if margin:
            cells_B1hw = F.max_pool2d(cells_B1hw, 2 * margin + 1, stride=1, padding=margin)
        rows.append(torch.where(cells_B1hw[:, 0] > 0, codes_BHW, background_codes_HW.to(codes_BHW)))
    canonical_NHW = torch.cat(rows)
    return canonical_NHW, float((canonical_NHW != codes_NHW).float().mean())


@torch.no_grad()
def contact_cells(codes_NHW: torch.Tensor, tokenizer: Any, background_3HW: torch.Tensor) -> torch.Tensor:
    """(N, H, W) bool: the cells of canonical-background codes (:func:`canonical_background`) that are
    not the no-contact image's own code there, i.e. the contact and its margin.  What
    ``generator.model.contact_weight`` asks the condition grid for."""
    background_codes_HW = tokenizer.encode_codes(background_3HW[None].to(tokenizer.device)).cpu()[0]
    if background_codes_HW.shape != codes_NHW.shape[1:]:
        raise ValueError(
            f"the background's code grid {tuple(background_codes_HW.shape)} is not the codes' "
            f"{tuple(codes_NHW.shape[1:])}"
        )
    return codes_NHW != background_codes_HW.to(codes_NHW)

"""Readers of public tactile datasets, each a `dataset` plugin.

One module per dataset layout: Touch and Go (``touch_and_go``), VisGel (``visgel``), TVL's HCT
and SSVTP parts (``tvl_hct``, ``tvl_ssvtp``), ObjectFolder-Real and the ObjectFolder
cross-generation benchmark (``objectfolder_real``, ``objectfolder_cross``), FabricVST
(``fabricvst``) and a generic class-folder or CSV reader (``image_folder``).  Every reader reads
the lists and CSVs that ship with its dataset, indexes and checks all samples when it is built
(files exist, pairs are consistent, labels are in range, the split is not empty) and decodes
images only in ``__getitem__``; shared image decoding, file checks and the lenient
skip-and-warn policy live in :mod:`vqtouch.plugins.data.readers._io` (the check of every image's
header when a reader is built in :mod:`vqtouch.plugins.data.readers._headers`).
"""

from __future__ import annotations

import importlib
from typing import Any

#: The readers' public helpers for image files, which other packages (the evaluation commands) use:
#: public name -> (module of this package, name there), imported on first use so that importing a
#: reader's plugin module stays light.
_PUBLIC = {
    "IMAGE_SUFFIXES": ("_io", "IMAGE_SUFFIXES"),
    "is_image_file": ("_io", "is_image_file"),
    "list_images": ("_io", "list_images"),
    "read_image_size": ("_io", "read_image_size"),
}

__all__ = sorted(_PUBLIC)


def __getattr__(name: str) -> Any:
    if name not in _PUBLIC:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    module, attribute = _PUBLIC[name]
    value = getattr(importlib.import_module(f"{__name__}.{module}"), attribute)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_PUBLIC])

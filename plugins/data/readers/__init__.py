"""Readers of public tactile datasets, each a `dataset` plugin.

One module per dataset layout: Touch and Go (``touch_and_go``), VisGel (``visgel``), TVL's HCT
and SSVTP parts (``tvl_hct``, ``tvl_ssvtp``), ObjectFolder-Real and the ObjectFolder
cross-generation benchmark (``objectfolder_real``, ``objectfolder_cross``), FabricVST
(``fabricvst``) and a generic class-folder or CSV reader (``image_folder``).  Every reader reads
the lists and CSVs that ship with its dataset, indexes and checks all samples when it is built
(files exist, pairs are consistent, labels are in range, the split is not empty) and decodes
images only in ``__getitem__``; shared image decoding, file checks and the lenient
skip-and-warn policy live in :mod:`vqtouch.plugins.data.readers._io`.
"""

from ._io import IMAGE_SUFFIXES, is_image_file, list_images, read_image_size

#: The readers' public helpers for image files, which other packages (the evaluation commands) use.
__all__ = ["IMAGE_SUFFIXES", "is_image_file", "list_images", "read_image_size"]

"""What the running command asked of image reading (``--allow-greyscale``, ``--lenient``).

Context variables the CLI sets around a command and the image loaders of :mod:`vqtouch.plugins.utils.images`
read; kept apart from them so the CLI sets them without importing torch."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from contextvars import ContextVar


_GREYSCALE_ALLOWED: ContextVar[bool] = ContextVar("greyscale_allowed", default=False)


@contextlib.contextmanager
def greyscale_allowed(allowed: bool = True) -> Iterator[None]:
    """Within the block, image loaders without their own ``allow_greyscale`` (the commands' folders of
    images, ``--visual`` files, ...) copy greyscale images into 3 channels instead of refusing them:
    what a command's ``--allow-greyscale`` does."""
    token = _GREYSCALE_ALLOWED.set(allowed)
    try:
        yield
    finally:
        _GREYSCALE_ALLOWED.reset(token)


_BAD_IMAGES_SKIPPED: ContextVar[bool] = ContextVar("bad_images_skipped", default=False)


@contextlib.contextmanager
def bad_images_skipped(skip: bool = True) -> Iterator[None]:
    """Within the block, a folder of a sensor's images drops the files that do not decode (with one
    warning naming them) instead of refusing the folder: what a command's ``--lenient`` does."""
    token = _BAD_IMAGES_SKIPPED.set(skip)
    try:
        yield
    finally:
        _BAD_IMAGES_SKIPPED.reset(token)


def skipping_bad_images() -> bool:
    """Whether the running command asked to skip images that do not decode (:func:`bad_images_skipped`)."""
    return _BAD_IMAGES_SKIPPED.get()

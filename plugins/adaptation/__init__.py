"""Cross-sensor stages: sensor-family clustering, unseen-sensor assignment and few-shot adaptation.

The public API other packages use (imported on first use, so importing this package stays light):
adapting a tokenizer to an unseen sensor (:func:`adapt_tokenizer` with :class:`AdaptSettings`, the
families it assigns from: :func:`families_to_adapt_from`, :func:`registered_source`), the unseen
sensor's images (:func:`target_images`) and its no-contact background (:func:`sensor_background`),
what an ``adapt.json`` holds (:class:`AdaptRecord`),
:class:`AdaptationRefused` and :func:`refuse_existing`.  Other packages import these names from
here, never the modules behind them (``make lint`` checks it).
"""

from __future__ import annotations

import importlib
from typing import Any

_PUBLIC = {
    "AdaptRecord": ("adapt", "AdaptRecord"),
    "AdaptSettings": ("stages_plugin", "AdaptSettings"),
    "AdaptationRefused": ("adapt_images", "AdaptationRefused"),
    "adapt_tokenizer": ("adapt", "adapt_tokenizer"),
    "families_to_adapt_from": ("adapt_families", "families_to_adapt_from"),
    "refuse_existing": ("adapt", "refuse_existing"),
    "sensor_background": ("adapt_images", "sensor_background"),
    "target_images": ("adapt_images", "target_images"),
    "registered_source": ("families", "registered_source"),
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

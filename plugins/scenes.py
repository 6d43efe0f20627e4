"""The paper's scenarios as scene presets.

A scene is a partial experiment config: the stages it runs and the plugin chosen for
each slot.  Slots whose plugins are not installed yet are left empty, and ``vqtouch
config show`` reports them; users fill them with ``--set`` or a config file.
"""

from __future__ import annotations

from vqtouch.core import hookimpl

_METRICS = [{"name": "psnr"}, {"name": "ssim"}]

SCENES: dict[str, tuple[str, dict]] = {
    "reconstruction": (
        "Train a tactile tokenizer and measure how well it reconstructs held-out images.",
        {"stages": ["tokenizer", "reconstruct", "evaluate"], "metrics": _METRICS},
    ),
    "few-shot": (
        "Adapt to an unseen sensor from a few images mixed 1:5 with its family's data, then generate for it.",
        {"stages": ["tokenizer", "cluster", "adapt", "generator", "evaluate"], "metrics": _METRICS,
         "conditioner": {"name": "label"}, "data": {"num_samples": 500}},
    ),
    "zero-shot": (
        "Assign an unseen sensor to its family without any of its images and reuse the family tokenizer.",
        {"stages": ["tokenizer", "cluster", "reconstruct", "evaluate"], "metrics": _METRICS},
    ),
    "cross-sensor": (
        "Train on one sensor, adapt and evaluate on another (e.g. GelSight -> GelSight Mini).",
        {"stages": ["tokenizer", "adapt", "reconstruct", "evaluate"], "metrics": _METRICS},
    ),
    "vision-to-touch": (
        "Generate the tactile image of a contact from a visual image of it (frozen CLIP condition).",
        {"stages": ["tokenizer", "generator", "evaluate"], "metrics": _METRICS,
         "conditioner": {"name": "clip"}},
    ),
    "label-to-touch": (
        "Generate tactile images of a given object class (label condition).",
        {"stages": ["tokenizer", "generator", "evaluate"], "metrics": _METRICS,
         "conditioner": {"name": "label"}},
    ),
    "touch-to-touch": (
        "Generate a tactile image for a target sensor from another tactile image (tactile condition).",
        {"stages": ["tokenizer", "generator", "evaluate"], "metrics": _METRICS,
         "conditioner": {"name": "tactile"}},
    ),
}


@hookimpl
def vqtouch_register_scenes(register):
    for name, (description, config) in SCENES.items():
        register(name, config, description=description)

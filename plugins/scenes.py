"""The paper's scenarios as scene presets.

A scene is a partial experiment config: the stages it runs and the plugin chosen for
each slot.  Slots whose plugins are not installed yet are left empty, and ``vqtouch
config show`` reports them; users fill them with ``--set`` or a config file.  A scene
names stages and plugins only: what each stage needs is declared by the stage itself.
"""

from __future__ import annotations

from vqtouch.core import hookimpl

#: Every scene's pairwise metrics.  LPIPS needs a weights file (VQTOUCH_LPIPS_VGG, ...): without it
#: the run reports it as skipped, with the file to provide.  FID and KID are left to the
#: distribution scores and `vqtouch evaluate`: a held-out split of a few dozen images gives no
#: meaningful FID.
_METRICS = [{"name": "psnr"}, {"name": "ssim"}, {"name": "ms_ssim"}, {"name": "lpips"}]
_DATA = {"dataset": {"name": "procedural"}}
#: The paper's tokenizer: DM-VQGAN + nearest-neighbour VQ, trained with a PatchGAN.  The lookup is
#: cosine in 8 dimensions (ViT-VQGAN): with the plain lookup, 512 codes collapsed to ~10 in use on
#: our 64-px GelSight scenes; with it ~400 are used and PSNR is ~3.5 dB higher at equal steps
#: (docs/guide.md, Tokenizers).
_TOKENIZER = {
    "autoencoder": {"name": "dm_vqgan"},
    "quantizer": {"name": "vq", "codebook_size": 512, "l2_normalize": True, "lookup_dim": 8},
    "discriminator": {"name": "patchgan"},
}
#: Sensor families by k-means over the tokenizer's pooled features, the family count by silhouette.
_CLUSTER = {"clusterer": {"name": "kmeans"}}
#: An unseen "derivative" GelSight: same family, drifted illumination and a slightly worn gel.
_GENERATOR = {"model": {"name": "vq_diffusion"}, "sampler": {"name": "posterior"}}
GELSIGHT_DERIVATIVE_I = {
    "name": "gelsight",
    "variant": {
        "colour_gain": [1.08, 0.95, 0.9],
        "illumination_shift": 0.03,
        "background_drift": 0.05,
        "wear_blur": 0.008,
        "noise_std": 0.01,
        "seed": 1,
    },
}
GELSIGHT_DERIVATIVE_II = {
    "name": "gelsight",
    "variant": {
        "colour_gain": [0.92, 1.05, 1.1],
        "response_scale": 0.8,
        "damage_spots": 2,
        "shift": [0.02, -0.01],
        "rotation_deg": 2.0,
        "noise_std": 0.01,
        "seed": 2,
    },
}

SCENES: dict[str, tuple[str, dict]] = {
    "tour": (
        "Every stage once (what `make demo` runs): a DM-VQGAN tokenizer and its reconstructions of real GelSight "
        "frames; sensor families and few-shot adaptation to an unseen GelSight (with the bundled tokenizer); one "
        "generator trained from a label, "
        "a visual image, a text and a GelSight Mini image of the same contact (one condition per step), which "
        "generates from each; then the bundled pretrained tokenizer and generator (trained longer than a demo can, "
        "shipped in the package) on the same held-out data.",
        {
            "tokenizer": _TOKENIZER,
            "stages": ["tokenizer", "reconstruct", "cluster", "adapt", "generator", "pretrained"],
            # Families and adaptation use the bundled tokenizer: one trained for the demo's minutes has too
            # little in its features to tell sensors apart (the report's captions say which tokenizer it was).
            "metrics": _METRICS,
            "cluster": _CLUSTER | {"family_tokenizer": "pretrained:tour"},
            "adapt": {"family_tokenizer": "pretrained:tour"},
            "generator": _GENERATOR
            | {"conditioners": [{"name": "label"}, {"name": "visual"}, {"name": "text_scratch"}, {"name": "tactile"}]},
            "sensor": {"name": "gelsight"},
            "paired_sensor": {"name": "gelsight_mini"},
            "target_sensor": GELSIGHT_DERIVATIVE_I,
            "data": _DATA,
        },
    ),
    "reconstruction": (
        "Train a tactile tokenizer and measure how well it reconstructs held-out images.",
        {
            "tokenizer": _TOKENIZER,
            "stages": ["tokenizer", "reconstruct"],
            "metrics": _METRICS,
            "sensor": {"name": "gelsight"},
            "data": _DATA,
        },
    ),
    "few-shot": (
        "Adapt to an unseen sensor from a few images mixed 1:5 with its family's data, then generate for it.",
        {
            "tokenizer": _TOKENIZER,
            "stages": ["tokenizer", "cluster", "adapt", "generator"],
            "metrics": _METRICS,
            "cluster": _CLUSTER,
            "generator": _GENERATOR | {"conditioners": [{"name": "label"}]},
            "sensor": {"name": "gelsight"},
            "target_sensor": GELSIGHT_DERIVATIVE_I,
            "data": {"dataset": {"name": "procedural", "num_samples": 500}},
        },
    ),
    "zero-shot": (
        "Assign an unseen sensor to its family without any of its images and reuse the family tokenizer.",
        {
            "tokenizer": _TOKENIZER,
            "stages": ["tokenizer", "cluster", "reconstruct"],
            "metrics": _METRICS,
            "cluster": _CLUSTER,
            "sensor": {"name": "gelsight"},
            "target_sensor": GELSIGHT_DERIVATIVE_II,
            "data": _DATA,
        },
    ),
    "cross-sensor": (
        "Train on one sensor, adapt and evaluate on another (e.g. GelSight -> GelSight Mini).",
        {
            "tokenizer": _TOKENIZER,
            "stages": ["tokenizer", "adapt", "reconstruct"],
            "metrics": _METRICS,
            "sensor": {"name": "gelsight"},
            "target_sensor": {"name": "gelsight_mini"},
            "data": _DATA,
        },
    ),
    "vision-to-touch": (
        "Generate the tactile image of a contact from a visual image of it (frozen EfficientNet-Lite0 condition; "
        "generator.conditioners.0.name=clip with local CLIP weights).",
        {
            "tokenizer": _TOKENIZER,
            "stages": ["tokenizer", "generator"],
            "metrics": _METRICS,
            "generator": _GENERATOR | {"conditioners": [{"name": "visual"}]},
            "sensor": {"name": "gelsight"},
            "data": _DATA,
        },
    ),
    "label-to-touch": (
        "Generate tactile images of a given object class (label condition).",
        {
            "tokenizer": _TOKENIZER,
            "stages": ["tokenizer", "generator"],
            "metrics": _METRICS,
            "generator": _GENERATOR | {"conditioners": [{"name": "label"}]},
            "sensor": {"name": "gelsight"},
            "data": _DATA,
        },
    ),
    "text-to-touch": (
        "Generate tactile images from a short text description (a text encoder trained from scratch).",
        {
            "tokenizer": _TOKENIZER,
            "stages": ["tokenizer", "generator"],
            "metrics": _METRICS,
            "generator": _GENERATOR | {"conditioners": [{"name": "text_scratch"}]},
            "sensor": {"name": "gelsight"},
            "data": _DATA,
        },
    ),
    "mixed-to-touch": (
        "One generator trained with a label, a visual image and a text, one condition per step; it generates "
        "from any of them.",
        {
            "tokenizer": _TOKENIZER,
            "stages": ["tokenizer", "generator"],
            "metrics": _METRICS,
            "generator": _GENERATOR
            | {"conditioners": [{"name": "label"}, {"name": "visual"}, {"name": "text_scratch"}]},
            "sensor": {"name": "gelsight"},
            "data": _DATA,
        },
    ),
    "touch-to-touch": (
        "Generate a DIGIT image of a contact from a GelSight image of the same contact (paired renders: the "
        "tokenizer and generator work in `sensor`, the condition is `paired_sensor`'s image; set "
        "sensor.name=gelsight_mini for GelSight -> GelSight Mini).",
        {
            "tokenizer": _TOKENIZER,
            "stages": ["tokenizer", "generator"],
            "metrics": _METRICS,
            "generator": _GENERATOR | {"conditioners": [{"name": "tactile"}]},
            "sensor": {"name": "digit"},
            "paired_sensor": {"name": "gelsight"},
            "data": _DATA,
        },
    ),
}


@hookimpl
def vqtouch_register_scenes(register):
    for name, (description, config) in SCENES.items():
        register(name, config, description=description)

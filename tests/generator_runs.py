"""Tiny generator pieces for tests, importable by any test module as ``import generator_runs``
(registered in conftest): the overrides of a tiny trained run (a 32 px label-to-touch run:
tokenizer 2 steps, generator 6 steps) and a tiny tokenizer checkpoint folder (the source
tokenizer of the ``tactile_codes`` conditioner)."""

from __future__ import annotations

from pathlib import Path

import torch

TINY = [
    "tokenizer.autoencoder.channels=16",
    "tokenizer.autoencoder.norm_groups=8",
    "tokenizer.autoencoder.channel_multipliers=[1,2]",
    "tokenizer.autoencoder.z_channels=16",
    "tokenizer.autoencoder.embed_dim=8",
    "tokenizer.quantizer.codebook_size=32",
    "data.image_size=32",
    "data.batch_size=4",
    "data.dataset.num_samples=24",
    "data.val_fraction=0.25",
    "tokenizer.train.steps=2",
    "tokenizer.loss.perceptual=none",
    "tokenizer.discriminator=null",
    'metrics=[{"name": "psnr"}]',
    "generator.model.depth=1",
    "generator.model.width=32",
    "generator.model.num_steps=20",
    "generator.train.steps=6",
    "generator.train.checkpoint_every=3",
    "generator.train.log_every=1",
    "generator.num_samples=4",
    "generator.steps=4",
]


#: A tiny VQGAN tokenizer run of the reconstruction scene (32 px, 2 steps, no GAN): the family
#: tokenizer of the cross-sensor and few-shot experiments' tests.
TINY_TOKENIZER = [
    "tokenizer.autoencoder.name=vqgan",
    "tokenizer.autoencoder.channels=16",
    "tokenizer.autoencoder.norm_groups=8",
    "tokenizer.autoencoder.channel_multipliers=[1,2]",
    "tokenizer.autoencoder.z_channels=16",
    "tokenizer.autoencoder.embed_dim=8",
    "tokenizer.quantizer.codebook_size=32",
    "data.image_size=32",
    "data.batch_size=4",
    "data.dataset.num_samples=16",
    "tokenizer.train.steps=2",
    "tokenizer.loss.perceptual=none",
    "tokenizer.discriminator=null",
]


def tiny_tokenizer_args(out: Path) -> list[str]:
    """``vqtouch train tokenizer`` arguments of the :data:`TINY_TOKENIZER` run in ``out``."""
    return [
        "--no-progress",
        "train",
        "tokenizer",
        "--scene",
        "reconstruction",
        "--out",
        str(out),
        *[item for override in TINY_TOKENIZER for item in ("--set", override)],
    ]


def train_args(out: Path, *extra: str, scene: str = "label-to-touch", flags: tuple[str, ...] = ()) -> list[str]:
    """``vqtouch train generator`` arguments of a tiny run in ``out``; ``extra`` overrides come last."""
    args = ["--no-progress", "train", "generator", "--scene", scene, "--out", str(out), *flags]
    for override in [*TINY, *extra]:
        args += ["--set", override]
    return args


def cluster_args(
    run: str | Path, out: str | Path, sensors: list[str], *, images: int = 8, image_size: int | None = None
) -> list[str]:
    """``vqtouch cluster`` arguments: ``sensors`` grouped into two families from ``images`` images each,
    with the tokenizer of ``run`` (at ``image_size`` where given)."""
    size = ["--image-size", str(image_size)] if image_size is not None else []
    return ["cluster", "--run", str(run), *size, "--images", str(images), "--out", str(out), "--families", "2",
            "--sensors", *sensors]  # fmt: skip


def tiny_tokenizer_folder(folder: Path) -> Path:
    """A checkpoint folder under ``folder`` holding a tiny untrained VQGAN tokenizer (autoencoder +
    16-code quantizer, built in the contract tests' default context: 32 px, 8 latent channels),
    made once per folder."""
    from vqtouch.core import load_plugins, save
    from vqtouch.plugins.testing import DEFAULT_CONTEXT

    path = folder / "tiny_tokenizer"
    if not (path / "quantizer.safetensors").is_file():
        host = load_plugins(autoload=False)
        path.mkdir(parents=True, exist_ok=True)
        with torch.random.fork_rng():  # the same weights on every run: tests that use them are repeatable
            torch.manual_seed(0)
            autoencoder = host.build(
                "autoencoder",
                {
                    "name": "vqgan",
                    "channels": 8,
                    "channel_multipliers": [1, 2],
                    "z_channels": 8,
                    "embed_dim": 8,
                    "norm_groups": 4,
                },
                DEFAULT_CONTEXT,
            )
            context = DEFAULT_CONTEXT.model_copy(update=autoencoder.context_facts())
            quantizer = host.build("quantizer", {"name": "vq", "codebook_size": 16}, context)
        save(autoencoder, path / "autoencoder.safetensors", host=host)
        save(quantizer, path / "quantizer.safetensors", host=host)
    return path

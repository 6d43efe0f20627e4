"""A fresh tokenizer trained from scratch on a sensor's images alone: the baseline an adaptation is
measured against (the cross-sensor cost, the few-shot scratch arm)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import torch

from vqtouch.core import PluginHost

from .adapt_images import ImageSet


def train_fresh_tokenizer(
    run: Any,
    images_N3HW: torch.Tensor,
    host: PluginHost,
    *,
    seed: int,
    steps: int | None = None,
    out: Path | None = None,
    metadata: dict[str, str] | None = None,
) -> tuple[Any, dict[str, Any]]:
    """A fresh tokenizer built from the run's config and trained with its objective and batch size
    on ``images_N3HW`` alone, for ``steps`` (default: the run's ``tokenizer.train.steps``): the
    baseline an adaptation is measured against.  Saved into ``out`` (autoencoder and quantizer,
    ``metadata`` in their headers) when given.  Returns the tokenizer, in eval mode, and
    ``{"steps", "seconds", "train_images", "batch_size"}``."""
    from vqtouch.core import Assembly, save
    from vqtouch.plugins.utils.seeding import resolve_device
    from vqtouch.plugins.runtime.run_dir import RunDir
    from vqtouch.plugins.training.trainer import Trainer
    from vqtouch.plugins.tokenizer import TOKENIZER_FILES, tokenizer_task
    from vqtouch.plugins.tokenizer import Tokenizer

    config = RunDir.open(run).load_config(host)
    assembly = Assembly(config, host)
    section = config.tokenizer
    # ``seed`` draws the initial weights too (repeatable; the seeds' spread covers them), leaving the
    # caller's random state as it was.
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        tokenizer = Tokenizer(assembly.component("tokenizer.autoencoder"), assembly.component("tokenizer.quantizer"))
        discriminator = (
            assembly.component("tokenizer.discriminator")
            if section.discriminator is not None and section.loss.adversarial_weight > 0
            else None
        )
    device = resolve_device(config.device)
    steps = section.train.steps if steps is None else steps
    # A set smaller than the run's batch still trains (few-shot arms): one batch then holds every image.
    batch_size = min(config.data.batch_size, len(images_N3HW))
    trainer = Trainer(
        tokenizer_task(tokenizer, section.loss, device, discriminator),
        ImageSet(images_N3HW),
        section.train.model_copy(update={"steps": steps, "keep_best": False}),
        batch_size=batch_size,
        seed=seed,
        device=device,
        checkpoint_dir=None,
        host=host,
        stage="scratch",
    )
    tic = time.perf_counter()
    trainer.fit()
    seconds = time.perf_counter() - tic
    tokenizer.eval()
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        for file, module in zip(TOKENIZER_FILES, (tokenizer.autoencoder, tokenizer.quantizer)):
            save(module, out / file, step=steps, host=host, metadata=metadata)
    return tokenizer, {
        "steps": steps,
        "seconds": round(seconds, 2),
        "train_images": len(images_N3HW),
        "batch_size": batch_size,
    }

"""``vqtouch train tokenizer``, ``vqtouch reconstruct`` and ``vqtouch evaluate reconstruction``."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from vqtouch.core import ConfigError, CheckpointError, RunDir, hookimpl, load, resolve_device, seed_everything
from vqtouch.core.assembly import build_context, enrich_context
from vqtouch.core.cli import add_config_arguments, command_group, config_from_args
from vqtouch.core.config import SLOT_KINDS, ExperimentConfig, validate_experiment
from vqtouch.core.data import split_dataset
from vqtouch.core.images import image_grid, save_png
from vqtouch.core.training import Trainer, latest_checkpoint

from .training import Tokenizer, TokenizerTask, build_tokenizer, evaluate_reconstruction


def _require(config: ExperimentConfig, host: Any, *paths: str) -> None:
    for path in paths:
        if config.slot(path) is None:
            choices = ", ".join(host.registry(SLOT_KINDS[path]).names()) or "none installed"
            raise ConfigError(f"{path} is not set; choose one with --set {path}.name=<{choices}>")


def _metrics(config: ExperimentConfig, host: Any, context: Any) -> dict[str, Any]:
    return {item.name: host.build("metric", item, context) for item in config.metrics}


def _save_examples(run_path: Path, examples: tuple[torch.Tensor, torch.Tensor], name: str) -> Path:
    originals, reconstructions = examples
    return save_png(image_grid(torch.cat([originals, reconstructions]), columns=len(originals)), run_path / name)


def _printable(scores: dict[str, Any]) -> dict[str, Any]:
    return {key: (round(value, 4) if isinstance(value, float) else value) for key, value in scores.items()
            if key != "examples"}


def train_tokenizer(config: ExperimentConfig, host: Any, run: RunDir, *, resume: bool = False) -> dict[str, Any]:
    """Train the configured tokenizer in ``run`` and evaluate it on the held-out split."""
    from .perceptual import build_perceptual_loss

    _require(config, host, "data.dataset", "tokenizer.encoder", "tokenizer.quantizer")
    device = resolve_device(config.device)
    seed_everything(config.seed, config.deterministic)
    context = build_context(config)
    dataset = host.build("dataset", config.data.dataset, context)
    context = enrich_context(context, dataset)
    train_set, val_set = split_dataset(dataset, config.data.val_fraction, config.seed)
    tokenizer, context = build_tokenizer(config, host, context)
    loss = config.tokenizer.loss
    discriminator = None
    if config.tokenizer.discriminator is not None and loss.adversarial_weight > 0:
        discriminator = host.build("discriminator", config.tokenizer.discriminator, context)
    perceptual = None
    if loss.perceptual != "none" and loss.perceptual_weight > 0:
        perceptual = build_perceptual_loss(loss.perceptual, loss.lpips_backbone, loss.lpips_heads,
                                           effnet_image_size=loss.perceptual_image_size).to(device)
    task = TokenizerTask(tokenizer, loss, discriminator, perceptual)
    trainer = Trainer(task, train_set, config.train, batch_size=config.data.batch_size, seed=config.seed,
                      device=device, checkpoint_dir=run.checkpoints, run=run, num_workers=config.data.num_workers,
                      host=host)
    if resume and trainer.resume(run.checkpoints):
        print(f"resumed {run.path} at step {trainer.state.step}")
    state = trainer.fit()
    scores = evaluate_reconstruction(tokenizer, val_set, _metrics(config, host, context), device=device,
                                     batch_size=config.data.batch_size)
    if trainer.dist.is_main:
        _save_examples(run.path, scores["examples"], "reconstructions.png")
        result = {"step": state.step, "skipped_steps": state.skipped_steps, "train_samples": len(train_set),
                  "val_samples": len(val_set), **_printable(scores)}
        run.write_json("eval.json", result)
    return scores


def _train_tokenizer_command(args: argparse.Namespace) -> int:
    from vqtouch.core import default_host

    host = default_host()
    if args.resume:
        run_path = Path(args.resume)
        if not (run_path / "config.json").is_file():
            raise ConfigError(f"--resume {run_path}: not a run directory (no config.json)")
        if args.overrides or args.config:
            raise ConfigError("--resume continues a run with its saved config; drop --set/--config")
        config = validate_experiment(json.loads((run_path / "config.json").read_text()), host)
        run = RunDir(run_path)
    else:
        config = config_from_args(args, host)
        run = RunDir.create(config, argv=args.argv, host=host, path=args.out)
    try:
        scores = train_tokenizer(config, host, run, resume=bool(args.resume))
    except KeyboardInterrupt:
        print(f"\ninterrupted; the checkpoint is saved. Resume with: vqtouch train tokenizer --resume {run.path}")
        return 130
    print(json.dumps(_printable(scores), indent=2))
    print(f"run: {run.path}  (reconstructions.png, eval.json, checkpoints/)")
    return 0


def load_tokenizer(run_or_folder: str | Path, host: Any, step: int | None = None,
                   device: str = "cpu") -> tuple[Tokenizer, Path]:
    """Load the encoder and quantizer of a run (latest or given step) or of a checkpoint folder."""
    path = Path(run_or_folder)
    if (path / "encoder.safetensors").is_file():
        folder = path
    else:
        checkpoints = path / "checkpoints"
        folder = checkpoints / f"step-{step:08d}" if step is not None else latest_checkpoint(checkpoints)
        if folder is None or not (folder / "encoder.safetensors").is_file():
            raise CheckpointError(f"{path}: no tokenizer checkpoint found (expected checkpoints/step-*/"
                                  f"encoder.safetensors); train one with `vqtouch train tokenizer`")
    encoder = load(folder / "encoder.safetensors", host=host, map_location=device)
    quantizer = load(folder / "quantizer.safetensors", host=host, map_location=device)
    return Tokenizer(encoder, quantizer).eval(), folder


def taxim_frames(sensor: str, image_size: int) -> torch.Tensor:
    """taxim's real frames of ``sensor`` as (N, 3, S, S) in [0, 1]: centre square, resized."""
    from vqtouch.sensors.gelsight import load_taxim_calibration

    calibration = load_taxim_calibration(sensor)
    with np.load(calibration.folder / "dataPack.npz", allow_pickle=False) as pack:
        frames = torch.from_numpy(pack["imgs"][..., ::-1].copy()).permute(0, 3, 1, 2).float() / 255
    rows, cols = frames.shape[-2:]
    left = (cols - rows) // 2
    square = frames[:, :, :, left:left + rows]
    return F.interpolate(square, size=(image_size, image_size), mode="bilinear", antialias=True, align_corners=False)


def _reconstruct_command(args: argparse.Namespace) -> int:
    from vqtouch.core import default_host

    host = default_host()
    tokenizer, folder = load_tokenizer(args.run, host, args.step)
    image_size = tokenizer.encoder.vqtouch_spec.context.image_size
    if args.taxim:
        images = taxim_frames(args.taxim, image_size)
        source = f"taxim {args.taxim} real frames"
    else:
        dataset = host.build("dataset", {"name": "image_folder", "root": args.images, "image_size": image_size})
        images = torch.stack([dataset[i]["tactile"] for i in range(len(dataset))])
        source = args.images
    metrics = {name: host.build("metric", name) for name in ("ssim", "psnr")}
    with torch.no_grad():
        reconstructions = torch.cat([tokenizer.reconstruct(images[i:i + 32])[0] for i in range(0, len(images), 32)])
    for metric in metrics.values():
        metric.update(reconstructions, images)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    count = min(8, len(images))
    save_png(image_grid(torch.cat([images[:count], reconstructions[:count]]), columns=count),
             out / "reconstructions.png")
    scores = {name: round(metric.compute(), 4) for name, metric in metrics.items()}
    (out / "reconstruct.json").write_text(json.dumps({"checkpoint": str(folder), "source": source,
                                                     "images": len(images), "image_size": image_size,
                                                     **scores}, indent=2) + "\n")
    print(f"{len(images)} images from {source} through {folder}: SSIM {scores['ssim']:.4f}, "
          f"PSNR {scores['psnr']:.2f} dB; pictures (top original, bottom reconstruction): {out}/reconstructions.png")
    return 0


def _evaluate_command(args: argparse.Namespace) -> int:
    from vqtouch.core import default_host

    host = default_host()
    run_path = Path(args.run)
    config = validate_experiment(json.loads((run_path / "config.json").read_text()), host)
    tokenizer, folder = load_tokenizer(run_path, host, args.step)
    context = enrich_context(build_context(config), tokenizer.encoder)
    if args.dataset:
        # A separate held-out dataset (e.g. another seed), evaluated whole: runs trained on
        # different amounts of data are then compared on the very same images.
        try:
            dataset_config = json.loads(args.dataset)
        except json.JSONDecodeError as exc:
            raise ConfigError(f"--dataset is not valid JSON: {exc}") from None
        evaluated = host.build("dataset", dataset_config, context)
    else:
        dataset = host.build("dataset", config.data.dataset, context)
        _, val_set = split_dataset(dataset, config.data.val_fraction, config.seed)
        evaluated = dataset if args.split == "all" else val_set
    names = args.metrics.split(",") if args.metrics else [m.name for m in config.metrics]
    metrics = {name: host.build("metric", name, context) for name in names}
    scores = evaluate_reconstruction(tokenizer, evaluated, metrics, batch_size=config.data.batch_size)
    _save_examples(run_path, scores["examples"], f"reconstructions_{folder.name}.png")
    result = {"checkpoint": str(folder), "split": "dataset" if args.dataset else args.split, **_printable(scores)}
    suffix = "_dataset" if args.dataset else ""
    (run_path / f"evaluation_{folder.name}{suffix}.json").write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    return 0


@hookimpl
def vqtouch_run_stage(stage, config, host, run):
    """The demo's tokenizer stage (train + held-out scores) and reconstruct stage (real frames)."""
    if stage == "tokenizer":
        scores = train_tokenizer(config, host, run)
        return {"steps": config.train.steps, **{k: v for k, v in _printable(scores).items()
                                                   if k in ("ssim", "psnr", "codebook_usage", "samples")},
                "picture": "reconstructions.png"}
    if stage == "reconstruct":
        tokenizer, _ = load_tokenizer(run.path, host)
        sensor = config.sensor.name if config.sensor is not None else ""
        if sensor not in ("gelsight", "gelsight_mini"):
            return None
        images = taxim_frames(sensor, tokenizer.encoder.vqtouch_spec.context.image_size)
        metrics = {name: host.build("metric", name) for name in ("ssim", "psnr")}
        with torch.no_grad():
            reconstructions = torch.cat([tokenizer.reconstruct(images[i:i + 16])[0] for i in range(0, len(images), 16)])
        for metric in metrics.values():
            metric.update(reconstructions, images)
        save_png(image_grid(torch.cat([images[:8], reconstructions[:8]]), columns=8), run.path / "real_frames.png")
        return {"source": f"{len(images)} real {sensor} frames (taxim)",
                **{name: round(metric.compute(), 4) for name, metric in metrics.items()}, "picture": "real_frames.png"}
    return None


@hookimpl
def vqtouch_add_commands(subparsers):
    train = command_group(subparsers, "train", "train a component (tokenizer, ...)")
    tokenizer = train.add_parser("tokenizer", help="train a tactile tokenizer (encoder + quantizer [+ GAN])")
    add_config_arguments(tokenizer, default_scene="reconstruction")
    tokenizer.add_argument("--out", help="run directory (default: <output_dir>/<name>-<time>-<hash>)")
    tokenizer.add_argument("--resume", metavar="RUN", help="continue an interrupted run from its last checkpoint")
    tokenizer.set_defaults(handler=_train_tokenizer_command)

    reconstruct = subparsers.add_parser("reconstruct", help="encode and decode images with a trained tokenizer")
    reconstruct.add_argument("--run", required=True, help="run directory (or a checkpoint folder)")
    reconstruct.add_argument("--step", type=int, help="checkpoint step (default: latest)")
    source = reconstruct.add_mutually_exclusive_group(required=True)
    source.add_argument("--taxim", choices=["gelsight", "gelsight_mini"], help="taxim's real frames of this sensor")
    source.add_argument("--images", help="an image folder (one sub-folder per class) to reconstruct")
    reconstruct.add_argument("--out", required=True, help="folder for reconstructions.png and reconstruct.json")
    reconstruct.set_defaults(handler=_reconstruct_command)

    evaluate = command_group(subparsers, "evaluate", "evaluate a trained component")
    recon = evaluate.add_parser("reconstruction", help="the paper's Table 1 metrics on the held-out split")
    recon.add_argument("--run", required=True, help="run directory of a trained tokenizer")
    recon.add_argument("--step", type=int, help="checkpoint step (default: latest)")
    recon.add_argument("--split", choices=["val", "all"], default="val", help="held-out split or all samples")
    recon.add_argument("--metrics", help="comma-separated metric plugins (default: the run's metrics)")
    recon.add_argument("--dataset", help="evaluate on this dataset (JSON config, used whole) instead of the run's "
                                         "held-out split, e.g. '{\"name\": \"procedural\", \"seed\": 999}'")
    recon.set_defaults(handler=_evaluate_command)

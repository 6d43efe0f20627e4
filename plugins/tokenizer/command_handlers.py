"""The tokenizer commands' handlers (their parsers are in commands.py): ``vqtouch train tokenizer``,
``vqtouch reconstruct`` and ``vqtouch evaluate reconstruction``."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

import torch

from vqtouch.plugins.runtime.outputs import output_folder
from vqtouch.core import Assembly, ConfigError
from vqtouch.plugins.evaluation.metric_set import MetricSet
from vqtouch.plugins.runtime.execution import run_stage
from vqtouch.plugins.runtime.interruptions import interrupted_message, interrupted_status
from vqtouch.plugins.runtime.run_dir import RunDir, is_main_process
from vqtouch.core.checkpoint import is_pretrained
from vqtouch.plugins.utils.image_options import skipping_bad_images
from vqtouch.plugins.cli.app import (
    config_from_args,
    plugin_block,
    stage_failure,
    training_run,
)
from vqtouch.core.config import parse_override, resolve_config
from vqtouch.plugins.utils.splits import experiment_split

from vqtouch.core.image_size import ImageSize, image_hw, size_text
from vqtouch.plugins.data.sensor_folders import folder_of, holds_images_directly, load_sensor_folder
from vqtouch.plugins.evaluation.contact import dataset_background

from .loading import tokenizer_location
from .stages import load_tokenizer, printable, reconstruct_all, save_pairs
from .training import evaluate_reconstruction


def cmd_train_tokenizer(args: argparse.Namespace) -> int:
    host = args.host
    run, config = training_run(args, host, stage="tokenizer")
    with run:  # releases the run's lock however the command ends
        try:
            outcome = run_stage("tokenizer", Assembly(config, host), run, resume=bool(args.resume))
        except KeyboardInterrupt as exc:
            print(f"\n{interrupted_message(exc, run, 'tokenizer')}", file=sys.stderr)
            return interrupted_status(exc)
    if outcome.status != "ran":
        raise stage_failure(outcome)
    if not is_main_process():
        return 0  # rank 0 writes eval.json (and may not have yet) and prints the result
    print(json.dumps(json.loads((run.path / "eval.json").read_text()), indent=2))
    outputs = [name for name in ("reconstructions.png", "eval.json") if (run.path / name).is_file()]
    print(f"run: {run.path}  ({', '.join([*outputs, 'checkpoints/'])})")
    return 0


def _images_dataset(images: str, options: list[str], image_size: ImageSize) -> dict[str, Any]:
    """The dataset block of ``reconstruct --images``: a folder read by ``image_folder``, or a JSON
    block of any reader; ``--images-option KEY=VALUE`` sets that reader's options (those its
    errors name, e.g. ``lenient=true``).  The image size is always the tokenizer's."""
    block = (
        plugin_block(images, "--images", default_name="image_folder")
        if images.strip().startswith("{")
        else {"name": "image_folder", "root": images}
    )
    for option in options:
        path, value = parse_override(option) if "=" in option else ([], None)
        if len(path) != 1 or path[0] in ("name", "image_size"):
            raise ConfigError(
                f"--images-option {option!r}: give one reader option as KEY=VALUE, e.g. lenient=true "
                "(the reader is chosen by --images and the image size by the tokenizer)"
            )
        block[path[0]] = value
    if "image_size" in block and block["image_size"] not in (image_size, list(image_hw(image_size))):
        raise ConfigError(
            f"--images sets image_size={block['image_size']}, but the tokenizer works at "
            f"{size_text(image_size)} px; "
            "drop image_size (images are resized to the tokenizer's size)"
        )
    if skipping_bad_images():
        block.setdefault("lenient", True)
    return {**block, "image_size": image_size}


def cmd_reconstruct(args: argparse.Namespace) -> int:
    host = args.host
    tokenizer, folder = load_tokenizer(args.run, host, args.step)
    image_size = tokenizer.autoencoder.vqtouch_spec.context.image_size
    if args.real_frames:
        sensor_config = host.validate("sensor_family", plugin_block(args.real_frames, "--real-frames"))
        images = host.build("sensor_family", sensor_config).reference_frames(*image_hw(image_size))
        if images is None:
            raise ConfigError(
                f"sensor family {sensor_config.name!r} declares no real reference frames; "
                "reconstruct your own with --images FOLDER"
            )
        source = f"real {sensor_config.name} frames"
    elif (frames_folder := folder_of(args.images)) is not None and holds_images_directly(frames_folder):
        # A sensor's frames in one folder (or a render export), read as cluster and adapt read them.
        if args.images_options:
            raise ConfigError(
                f"--images-option sets an option of the image_folder reader; {frames_folder} holds its images directly "
                "(no class sub-folders), so no reader is used: drop --images-option (--lenient and --allow-greyscale "
                "work on such a folder)"
            )
        images, source = load_sensor_folder(frames_folder, host, image_size), args.images
    else:
        dataset = host.build("dataset", _images_dataset(args.images, args.images_options, image_size))
        images = torch.stack([dataset[i]["tactile"] for i in range(len(dataset))])
        source = args.images
    metrics = MetricSet((name, host.build("metric", name)) for name in ("ssim", "psnr"))
    reconstructions = reconstruct_all(tokenizer, images, batch_size=32)
    scores = metrics.score(reconstructions, images)
    out = output_folder(args.out)
    save_pairs(images, reconstructions, out / "reconstructions.png")
    (out / "reconstruct.json").write_text(
        json.dumps(
            {"checkpoint": str(folder), "source": source, "images": len(images), "image_size": image_size, **scores},
            indent=2,
        )
        + "\n"
    )
    print(
        f"{len(images)} images from {source} through {folder}: SSIM {scores['ssim']:.4f}, "
        f"PSNR {scores['psnr']:.2f} dB; pictures (top original, bottom reconstruction): {out}/reconstructions.png"
    )
    return 0


def cmd_evaluate_reconstruction(args: argparse.Namespace) -> int:
    host = args.host
    if args.out:
        return _reconstruction_experiment_command(args)
    if args.overrides or args.config:
        raise ConfigError("--set and --config shape the experiment (--out); with --run the run's own config is used")
    location = tokenizer_location(args.run, host)
    if isinstance(location, RunDir):
        run = location
        config = run.load_config(host)
        tokenizer, folder = load_tokenizer(run, host, args.step)
    else:
        # A tokenizer folder outside any run (what `vqtouch adapt` writes, or a copied checkpoint folder)
        # has no data split of its own: --dataset names the images, the reconstruction scene the metrics.
        if not args.dataset:
            raise ConfigError(
                f"{location} is a tokenizer folder outside any run (e.g. a `vqtouch adapt` output): it has no "
                'data of its own; name the images with --dataset, e.g. --dataset \'{"name": "image_folder", '
                '"root": "data/my_sensor"}\''
            )
        if args.step is not None or args.split != "val":
            raise ConfigError(f"--step and --split choose within a run; {location} is one tokenizer folder")
        tokenizer, folder = load_tokenizer(location, host)
        image_size = tokenizer.autoencoder.vqtouch_spec.context.image_size
        config = resolve_config("reconstruction", [], [f"data.image_size={json.dumps(image_size)}"], host=host)
        run = RunDir(folder)  # written into as a run is, its scores beside the weights
    assembly = Assembly(config, host)
    if args.dataset:
        # A separate held-out dataset (e.g. another seed), evaluated whole: runs trained on
        # different amounts of data are then compared on the very same images.  Its own images give
        # the background (it may come from another sensor than the run's; it has no training split).
        evaluated = assembly.dataset(plugin_block(args.dataset, "--dataset"))
        background_images = evaluated
    else:
        dataset = assembly.component("data.dataset")
        background_images, val_set = experiment_split(dataset, config.data, config.seed)
        evaluated = dataset if args.split == "all" else val_set
    names = args.metrics.split(",") if args.metrics else [m.name for m in config.metrics]
    metrics = {name: assembly.build("metric", name) for name in names}
    background, background_source = dataset_background(
        background_images, image_hw(config.data.image_size), images_are="evaluated" if args.dataset else "training"
    )
    scores = evaluate_reconstruction(
        tokenizer, evaluated, metrics, batch_size=config.data.batch_size, background_3HW=background
    )
    result = {
        "checkpoint": str(folder),
        "split": "dataset" if args.dataset else args.split,
        "background": background_source,
        **printable(scores),
    }
    print(json.dumps(result, indent=2))  # first: a run that cannot be written to still gives its scores
    if is_pretrained(args.run) or not os.access(run.path, os.W_OK):
        what = f"{args.run} is a bundle, read-only" if is_pretrained(args.run) else f"{run.path} is read-only"
        print(f"vqtouch: {what}: the scores above were printed, not saved", file=sys.stderr)
        return 0
    if run.path == folder:  # a folder outside a run: one checkpoint, scored on --dataset
        picture, record = "reconstructions_dataset.png", "evaluation_dataset.json"
    else:  # a run names its files by checkpoint
        suffix = "_dataset" if args.dataset else ""
        picture, record = f"reconstructions_{folder.name}.png", f"evaluation_{folder.name}{suffix}.json"
    save_pairs(*scores["examples"], run.path / picture)
    run.write_json(record, result)
    return 0


def _reconstruction_experiment_command(args: argparse.Namespace) -> int:
    from .experiment import evaluate_reconstruction_experiment

    if args.step is not None or args.dataset or args.metrics or args.split != "val":
        raise ConfigError(
            "--step, --split, --metrics and --dataset score one run (--run); the experiment (--out) "
            "trains its own runs and scores them with the scene's metrics"
        )
    config = config_from_args(args, args.host)
    held_out = args.held_out
    if held_out is None and config.data.dataset is not None and "num_samples" in type(config.data.dataset).model_fields:
        held_out = 200
    out = Path(args.out)
    evaluate_reconstruction_experiment(
        config,
        args.host,
        out,
        seeds=args.seeds,
        samples=args.samples,
        models=args.models,
        mae_ratios=args.mae_ratios,
        held_out=held_out,
        distribution=args.distribution,
        overwrite=args.overwrite,
        report=lambda line: print(line, flush=True),
    )
    print((out / "reconstruction.md").read_text())
    print(f"-> {out} (reconstruction.json, reconstruction.md, reconstruction.png, reconstruction_samples.png, runs/)")
    return 0

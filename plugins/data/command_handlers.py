"""The ``vqtouch data`` commands' handlers (the parsers are in commands.py): render procedural scenes to a
folder, check the sensors against real frames and a split for leakage."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import torch

from vqtouch.core import ConfigError, PluginHost, VqtouchError
from vqtouch.core.checkpoint import atomic_write
from vqtouch.plugins.cli.app import plugin_block
from vqtouch.plugins.utils.splits import split_dataset
from vqtouch.plugins.utils.images import image_grid, save_png
from vqtouch.plugins.runtime.outputs import output_folder

from .export import export_samples


def cmd_render(args: argparse.Namespace) -> int:
    host = args.host
    out = Path(args.out)
    if out.exists() and any(out.iterdir()) and not args.overwrite:
        raise ConfigError(f"{out} exists and is not empty; choose another --out or pass --overwrite")
    config = {
        "name": "procedural",
        "num_samples": args.n,
        "image_size": args.image_size,
        "seed": args.seed,
        "cache": False,
    }
    if args.classes:
        config["classes"] = [name.strip() for name in args.classes.split(",") if name.strip()]
    sensor_config = host.validate("sensor_family", args.sensor)
    dataset = host.build("dataset", config, sensor=host.build("sensor_family", sensor_config))
    record = export_samples(dataset, range(len(dataset)), out, batch_size=args.batch_size)
    record["sensor"] = sensor_config.model_dump(mode="json")
    atomic_write(out / "render.json", lambda tmp: tmp.write_text(json.dumps(record, indent=2) + "\n"))
    print(
        f"wrote {record['samples']} samples to {out} ({record['images_per_second']} samples/s); "
        f"index: {out / 'index.csv'}"
    )
    return 0


def cmd_fidelity(args: argparse.Namespace) -> int:
    from vqtouch.sensors.fidelity import evaluate_fidelity

    host = args.host
    out = output_folder(args.out)
    results = []
    for sensor in args.sensors:
        result = evaluate_fidelity(sensor, host, resolution=(args.height, args.height * 4 // 3), crop_px=args.crop)
        count = min(8, result.frames)
        picture = image_grid(torch.cat([result.real_crops[:count], result.rendered_crops[:count]]), columns=count)
        save_png(picture, out / f"real_vs_rendered_{sensor}.png")
        results.append(result.summary())
        summary = result.summary()
        print(
            f"{sensor:14s} SSIM {summary['ssim']:.4f}  PSNR {summary['psnr_db']:.2f} dB   "
            f"(background only: SSIM {summary['background_only_ssim']:.4f}, "
            f"PSNR {summary['background_only_psnr_db']:.2f} dB; {summary['frames']} real frames, "
            f"{args.crop}px crops at {summary['resolution'][0]}x{summary['resolution'][1]})"
        )
    atomic_write(out / "fidelity.json", lambda tmp: tmp.write_text(json.dumps(results, indent=2) + "\n"))
    print(f"pictures (top row real, bottom row rendered): {out}/real_vs_rendered_<sensor>.png")
    return 0


def _build_dataset(host: PluginHost, text: str, flag: str, sensor: dict[str, Any]) -> Any:
    """The dataset ``text`` names, built as an experiment would (with ``sensor`` if it renders one);
    every error names ``flag``."""
    try:
        config = host.validate("dataset", plugin_block(text, flag))
    except VqtouchError as exc:
        raise type(exc)(f"{flag}: {exc}") from None
    inputs = {}
    if "sensor" in host.registry("dataset").get(config.name).inputs:
        try:
            inputs["sensor"] = host.build("sensor_family", sensor)
        except VqtouchError as exc:
            raise type(exc)(f"--sensor: {exc}") from None
    try:
        dataset = host.build("dataset", config, **inputs)
    except VqtouchError as exc:
        raise type(exc)(f"{flag}: {exc}") from None
    if len(dataset) == 0:
        raise ConfigError(f"{flag}: dataset {config.name!r} has no samples; point it at a folder with images")
    return dataset


def _check_leakage_arguments(args: argparse.Namespace) -> None:
    """A ConfigError naming the first ``vqtouch data leakage`` option out of range, or the inputs missing."""
    if args.dataset and (args.train or args.test):
        raise ConfigError(
            "give --dataset SPEC (to check its train/held-out split) or --train SPEC --test SPEC, not both"
        )
    if not args.dataset and not (args.train and args.test):
        raise ConfigError(
            "give --dataset SPEC to check the train/held-out split of one dataset, or both --train SPEC and --test SPEC"
        )
    if not 0 < args.val_fraction < 1:
        raise ConfigError(
            f"--val-fraction {args.val_fraction:g}: give a fraction between 0 and 1 (the held-out "
            "share to check; experiments hold out data.val_fraction)"
        )
    if args.threshold < 0:
        raise ConfigError(f"--threshold {args.threshold:g}: give a mean absolute difference >= 0, in 8-bit levels")
    if not 4 <= args.size <= 256:
        raise ConfigError(f"--size {args.size}: give a comparison side from 4 to 256 px")
    if args.fail_above is not None and not 0 <= args.fail_above <= 1:
        raise ConfigError(f"--fail-above {args.fail_above:g}: give the largest acceptable share, from 0 to 1")
    if args.show < 0:
        raise ConfigError(f"--show {args.show}: give how many closest pairs to list, 0 or more")


def cmd_leakage(args: argparse.Namespace) -> int:
    from .leakage import check_leakage, closest_pairs_picture, read_thumbnails

    host = args.host
    _check_leakage_arguments(args)
    record: dict[str, Any] = {}
    if args.dataset:
        dataset = _build_dataset(host, args.dataset, "--dataset", args.sensor)
        train, test = split_dataset(dataset, args.val_fraction, args.seed)
        everything = read_thumbnails(dataset, args.size)
        train_images, test_images = everything.select(train.indices), everything.select(test.indices)
        record["dataset"] = dataset.vqtouch_spec.config.model_dump(mode="json")
        record["split"] = {"val_fraction": args.val_fraction, "seed": args.seed, "unit": test.split_unit}
        print(
            f"dataset {record['dataset']['name']!r}, {len(dataset)} samples, split by {test.split_unit} "
            f"(val_fraction {args.val_fraction:g}, seed {args.seed}): {len(train)} train, {len(test)} held out"
        )
    else:
        train = _build_dataset(host, args.train, "--train", args.sensor)
        test = _build_dataset(host, args.test, "--test", args.sensor)
        train_images = read_thumbnails(train, args.size, "reading train images")
        test_images = read_thumbnails(test, args.size, "reading test images")
        record["train"] = train.vqtouch_spec.config.model_dump(mode="json")
        record["test"] = test.vqtouch_spec.config.model_dump(mode="json")
        print(
            f"train: dataset {record['train']['name']!r}, {len(train)} samples; "
            f"test: dataset {record['test']['name']!r}, {len(test)} samples"
        )
    report = check_leakage(train_images, test_images, args.threshold)
    quantiles = ", ".join(f"{name} {value:g}" for name, value in report.quantiles().items())
    print(
        f"distance to the nearest train image (mean absolute difference, 8-bit levels at {args.size}x{args.size}): "
        f"{quantiles}"
    )
    print(report.summary())
    closest = report.closest(args.show)
    if closest:
        print("closest pairs (distance, test id, nearest train id):")
        for test_index, train_index, distance in closest:
            marker = "*" if distance <= args.threshold else " "
            print(f"  {distance:8.3f}{marker} {report.test_ids[test_index]}  {report.train_ids[train_index]}")
    if args.out:
        out = output_folder(args.out)
        record |= report.to_json()
        atomic_write(out / "leakage.json", lambda tmp: tmp.write_text(json.dumps(record, indent=2) + "\n"))
        if closest:
            save_png(closest_pairs_picture(report, train, test, len(closest)), out / "closest_pairs.png")
            print(
                f"wrote {out / 'leakage.json'}, {out / 'closest_pairs.png'} (picture: test images on top, their "
                "nearest train images below)"
            )
        else:
            print(f"wrote {out / 'leakage.json'}")
    if args.fail_above is not None and report.near_duplicate_fraction > args.fail_above:
        print(
            f"near-duplicate share {report.near_duplicate_fraction:.1%} is above --fail-above "
            f"{args.fail_above:g}: failing"
        )
        return 1
    return 0

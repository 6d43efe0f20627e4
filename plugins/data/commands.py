"""``vqtouch data``: export procedural datasets and check the sensors against real frames.

- ``vqtouch data render --sensor gelsight_mini --n 500 --out DIR`` writes a browsable folder:
  ``tactile/<id>.png``, ``visual/<id>.png``, ``index.csv`` (``path,label,visual`` plus class,
  text, sensor and depth; readable by the ``image_folder`` dataset), ``classes.txt``,
  ``preview.png`` and ``render.json`` (the exact dataset config and the timing).
- ``vqtouch data fidelity --out DIR`` renders taxim's real GelSight / GelSight Mini ball
  presses, prints SSIM and PSNR against the real frames, and saves real | rendered pictures.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import torch

from vqtouch.core import ConfigError, hookimpl
from vqtouch.core.checkpoint import atomic_write
from vqtouch.core.images import image_grid, save_png
from vqtouch.core.image_size import image_size_argument

from .export import export_samples


def _sensor_argument(text: str) -> Any:
    """``--sensor`` takes a family name or a JSON object (family plus options and variant)."""
    text = text.strip()
    if text.startswith("{"):
        try:
            return json.loads(text)
        except json.JSONDecodeError as exc:
            raise argparse.ArgumentTypeError(f"--sensor is not valid JSON: {exc}") from None
    return {"name": text}


def _render_command(args: argparse.Namespace) -> int:
    host = args.host
    out = Path(args.out)
    if out.exists() and any(out.iterdir()) and not args.overwrite:
        raise ConfigError(f"{out} exists and is not empty; choose another --out or pass --overwrite")
    config = {"name": "procedural", "num_samples": args.n, "image_size": args.image_size, "seed": args.seed,
              "cache": False}
    if args.classes:
        config["classes"] = [name.strip() for name in args.classes.split(",") if name.strip()]
    sensor_config = host.validate("sensor_family", args.sensor)
    dataset = host.build("dataset", config, sensor=host.build("sensor_family", sensor_config))
    record = export_samples(dataset, range(len(dataset)), out, batch_size=args.batch_size)
    record["sensor"] = sensor_config.model_dump(mode="json")
    atomic_write(out / "render.json", lambda tmp: tmp.write_text(json.dumps(record, indent=2) + "\n"))
    print(f"wrote {record['samples']} samples to {out} ({record['images_per_second']} samples/s); "
          f"index: {out / 'index.csv'}")
    return 0


def _fidelity_command(args: argparse.Namespace) -> int:
    from vqtouch.sensors.fidelity import evaluate_fidelity

    host = args.host
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = []
    for sensor in args.sensors:
        result = evaluate_fidelity(sensor, host, resolution=(args.height, args.height * 4 // 3), crop_px=args.crop)
        count = min(8, result.frames)
        picture = image_grid(torch.cat([result.real_crops[:count], result.rendered_crops[:count]]), columns=count)
        save_png(picture, out / f"real_vs_rendered_{sensor}.png")
        results.append(result.summary())
        summary = result.summary()
        print(f"{sensor:14s} SSIM {summary['ssim']:.4f}  PSNR {summary['psnr_db']:.2f} dB   "
              f"(background only: SSIM {summary['background_only_ssim']:.4f}, "
              f"PSNR {summary['background_only_psnr_db']:.2f} dB; {summary['frames']} real frames, "
              f"{args.crop}px crops at {summary['resolution'][0]}x{summary['resolution'][1]})")
    atomic_write(out / "fidelity.json", lambda tmp: tmp.write_text(json.dumps(results, indent=2) + "\n"))
    print(f"pictures (top row real, bottom row rendered): {out}/real_vs_rendered_<sensor>.png")
    return 0


@hookimpl
def vqtouch_add_commands(subparsers):
    data = subparsers.add_parser("data", help="export procedural datasets; check sensors against real frames")
    data_sub = data.add_subparsers(dest="data_command", metavar="ACTION", required=True)

    render = data_sub.add_parser("render", help="render procedural (tactile, visual, label, text) samples to a folder")
    render.add_argument("--sensor", type=_sensor_argument, default={"name": "gelsight"},
                        help='sensor family name, or JSON such as \'{"name": "gelsight", "variant": {"noise_std": 0.02}}\'')
    render.add_argument("--n", type=int, default=500, help="number of samples (default 500)")
    render.add_argument("--out", required=True, help="output folder")
    render.add_argument("--image-size", type=image_size_argument, default=64,
                        help="image size: a side S, or HEIGHTxWIDTH such as 240x320 (default 64)")
    render.add_argument("--seed", type=int, default=0, help="dataset seed (default 0)")
    render.add_argument("--classes", help="comma-separated object classes (default: all 12)")
    render.add_argument("--batch-size", type=int, default=32, help="samples rendered per step (default 32)")
    render.add_argument("--overwrite", action="store_true", help="allow writing into a non-empty folder")
    render.set_defaults(handler=_render_command)

    fidelity = data_sub.add_parser("fidelity", help="SSIM/PSNR of rendered vs real taxim ball presses, with pictures")
    fidelity.add_argument("--out", required=True, help="folder for the pictures and fidelity.json")
    fidelity.add_argument("--sensors", nargs="+", default=["gelsight", "gelsight_mini"],
                          choices=["gelsight", "gelsight_mini"], help="sensors to check")
    fidelity.add_argument("--height", type=int, default=240, help="render height (width is 4/3 of it)")
    fidelity.add_argument("--crop", type=int, default=64, help="side of the square crop around each contact")
    fidelity.set_defaults(handler=_fidelity_command)

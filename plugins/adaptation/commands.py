"""``vqtouch cluster``: group sensors into families from a trained tokenizer's features.

::

    vqtouch cluster --run TOKRUN --sensors gelsight gelsight_mini digit '{"name": "gelsight", "variant": {...}}' \\
        path/to/real_sensor_frames --out DIR [--images 64] [--features pooled|codes] [--clusterer kmeans]

writes ``DIR/cluster.json`` (families, members, prototypes, the family distance matrix, each
sensor's distance to every family, and with ``--unseen SPEC ...`` where each unseen sensor is
assigned, or why it is refused) and ``DIR/families.png`` (a 2-D PCA embedding of every image's
features with the sensors' prototypes).  See :mod:`.families` for the method.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from vqtouch.core import ConfigError, hookimpl
from vqtouch.core.checkpoint import atomic_write
from vqtouch.core.cli import add_step_argument


def _positive(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text}: must be a positive integer")
    return value


def _fraction(text: str) -> float:
    value = float(text)
    if not 0 < value <= 1:
        raise argparse.ArgumentTypeError(f"{text}: must lie in (0, 1]")
    return value


def _non_negative(text: str) -> int:
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text}: must be 0 or more")
    return value


def _cluster_command(args: argparse.Namespace) -> int:
    from vqtouch.core import RunDir
    from vqtouch.plugins.tokenizer.stages import load_tokenizer

    from .families import (assign_to_family, cluster_prototypes, image_features, plot_families, sensor_images,
                           sensor_prototype)

    host = args.host
    if len(args.sensors) < 2:
        raise ConfigError("--sensors: give at least two sensors to group into families")
    tokenizer, folder = load_tokenizer(args.run, host, step=args.step)
    run = RunDir.open(args.run) if (Path(args.run) / "config.json").is_file() else None
    image_size = args.image_size or (run.load_config(host).data.image_size if run else 64)
    clusterer = host.build("clusterer", {"name": args.clusterer, "num_families": args.families})
    names, sources, features, prototypes = [], [], [], []
    for spec in args.sensors:
        sensor = sensor_images(spec, host, count=args.images, image_size=image_size, seed=args.seed)
        name = sensor.name if sensor.name not in names else f"{sensor.name}#{len(names)}"
        rows = image_features(tokenizer, sensor.images, args.features)
        names.append(name)
        sources.append(sensor.source)
        features.append(rows)
        prototypes.append(sensor_prototype(rows, args.refine_steps, args.keep))
        print(f"{name}: {len(rows)} images", flush=True)
    prototypes_SF = torch.stack(prototypes)
    unseen = []
    for spec in args.unseen:
        sensor = sensor_images(spec, host, count=args.images, image_size=image_size, seed=args.seed + 1)
        unseen.append((sensor, sensor_prototype(image_features(tokenizer, sensor.images, args.features),
                                                args.refine_steps, args.keep)))
    result = {"tokenizer": str(folder), "features": args.features, "images_per_sensor": args.images,
              "image_size": image_size, "clusterer": clusterer.vqtouch_spec.config.model_dump(mode="json"),
              "sensors": [{"name": n, "source": s, "images": len(f)} for n, s, f in zip(names, sources, features)],
              **cluster_prototypes(names, prototypes_SF, clusterer),
              "prototypes": {name: [round(float(v), 6) for v in row] for name, row in zip(names, prototypes_SF)}}
    threshold = args.threshold if args.threshold is not None else result["refusal_threshold"]
    result["assignments"] = {sensor.name: {"source": sensor.source, **assign_to_family(clusterer, prototype, threshold)}
                             for sensor, prototype in unseen}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write(out / "cluster.json", lambda tmp: tmp.write_text(json.dumps(result, indent=2) + "\n"))
    plot_families(names, features, prototypes_SF, [result["sensor_family"][n] for n in names],
                  out / "families.png", f"{len(result['families'])} families of {len(names)} sensors "
                                        f"({args.features} features, {args.clusterer})")
    for index, members in enumerate(result["families"]):
        print(f"family {index}: {', '.join(members)}")
    for name, assigned in result["assignments"].items():
        verdict = (f"refused: {min(assigned['distances']):.4g} from the nearest family, beyond the threshold "
                   f"{assigned['threshold']:.4g}" if assigned["refused"] else
                   f"family {assigned['family']} (margin {assigned['margin']:.4g})")
        print(f"unseen {name}: {verdict}")
    print(f"-> {out} (cluster.json, families.png)")
    return 0


@hookimpl
def vqtouch_add_commands(subparsers):
    cluster = subparsers.add_parser("cluster", help="group sensors into families from a trained tokenizer's features")
    cluster.add_argument("--run", required=True, help="a run whose tokenizer trained (or a checkpoint folder)")
    add_step_argument(cluster)
    cluster.add_argument("--sensors", nargs="+", required=True, metavar="SPEC",
                         help="sensors: registered family names, JSON with a variant, or folders of images")
    cluster.add_argument("--out", required=True, help="folder for cluster.json and families.png")
    cluster.add_argument("--images", type=_positive, default=64, help="images per sensor (default 64)")
    cluster.add_argument("--image-size", type=_positive, help="image side (default: the run's data.image_size)")
    cluster.add_argument("--features", choices=("pooled", "codes"), default="pooled",
                         help="pooled encoder features or code histograms (default pooled)")
    cluster.add_argument("--clusterer", default="kmeans", help="clusterer plugin (default kmeans)")
    cluster.add_argument("--families", type=_non_negative, default=0, help="number of families (0: chosen by silhouette)")
    cluster.add_argument("--refine-steps", type=_non_negative, default=3, help="prototype refinement steps (default 3)")
    cluster.add_argument("--keep", type=_fraction, default=0.8, help="fraction of images kept per refinement step")
    cluster.add_argument("--seed", type=int, default=0, help="seed of the rendered scenes")
    cluster.add_argument("--unseen", nargs="+", default=[], metavar="SPEC",
                         help="sensors to assign to the fitted families without joining them (zero-shot)")
    cluster.add_argument("--threshold", type=float,
                         help="refuse an unseen sensor farther than this from every family (default: 3x the "
                              "largest within-family spread, at least half the nearest two families' distance)")
    cluster.set_defaults(handler=_cluster_command)

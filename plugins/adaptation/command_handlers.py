"""The cross-sensor commands' handlers (their parsers are in commands.py): ``vqtouch cluster``, ``vqtouch adapt``,
``vqtouch evaluate cross-sensor``, ``vqtouch evaluate fewshot`` and ``vqtouch evaluate mix-ratio``."""

from __future__ import annotations

import argparse
from pathlib import Path

from vqtouch.core import ConfigError
from vqtouch.plugins.tokenizer import load_tokenizer

from .adapt import AdaptSettings


def cmd_cluster(args: argparse.Namespace) -> int:

    from .families import fit_families, save_families, sensor_images

    host = args.host
    if len(args.sensors) < 2:
        raise ConfigError("--sensors: give at least two sensors to group into families")
    tokenizer, folder = load_tokenizer(args.run, host, step=args.step)
    image_size = args.image_size or tokenizer.autoencoder.vqtouch_spec.context.image_size
    clusterer = host.build("clusterer", {"name": args.clusterer, "num_families": args.families})
    families = fit_families(
        tokenizer,
        args.sensors,
        host,
        clusterer=clusterer,
        images=args.images,
        image_size=image_size,
        features=args.features,
        refine_steps=args.refine_steps,
        keep=args.keep,
        seed=args.seed,
        tokenizer_source=str(folder),
        report=lambda line: print(line, flush=True),
    )
    assignments, plotted = {}, []
    for spec in args.unseen:
        sensor = sensor_images(spec, host, count=args.images, image_size=image_size, seed=args.seed + 1)
        assigned, shown = families.unseen(tokenizer, sensor.name, sensor.images, args.threshold)
        assignments[sensor.name] = {"source": sensor.source, **assigned}
        plotted.append(shown)
    out = Path(args.out)
    save_families(families, out, host, {"assignments": assignments}, plotted)
    for index, members in enumerate(families.summary["families"]):
        print(f"family {index}: {', '.join(members)}")
    uncertain = families.summary.get("family_count", {}).get("uncertain")
    if uncertain:
        print(f"note: {uncertain}")
    for name, assigned in assignments.items():
        print(f"unseen {name}: {describe_assignment(assigned)}")
    print(f"-> {out} (cluster.json, clusterer.safetensors, families.png)")
    return 0


def describe_assignment(assigned: dict) -> str:
    """One line: the family an unseen sensor joins and the margin, or why it is refused."""
    if assigned["refused"]:
        return (
            f"refused: {min(assigned['distances']):.4g} from the nearest family, beyond the threshold "
            f"{assigned['threshold']:.4g}"
        )
    return f"family {assigned['family']} (distance {min(assigned['distances']):.4g}, margin {assigned['margin']:.4g})"


def cmd_adapt(args: argparse.Namespace) -> int:

    from .adapt import adapt_tokenizer, refuse_existing
    from .adapt_families import families_to_adapt_from
    from .families import registered_source

    host = args.host
    out = Path(args.out)
    refuse_existing(out, args.overwrite)  # before the clustering, which takes a while
    tokenizer, folder = load_tokenizer(args.run, host, step=args.step)
    if not args.families:
        print("no --families: clustering the registered sensor families and 3 variants of each", flush=True)
    families = families_to_adapt_from(
        tokenizer,
        folder,
        host,
        families=Path(args.families) if args.families else None,
        where=f"the families in {args.families}",
        exclude=registered_source(args.images),
        seed=args.seed,
    )
    settings = AdaptSettings(
        shots=args.shots,
        ratio=args.ratio,
        steps=args.steps,
        learning_rate=args.learning_rate,
        batch_size=args.batch_size,
        eval_images=args.eval_images,
        threshold=args.threshold,
        family=args.family,
        seed=args.seed,
        part=args.part,
    )
    summary = adapt_tokenizer(
        args.run,
        args.images,
        families,
        host,
        out,
        settings,
        step=args.step,
        overwrite=args.overwrite,
        report=lambda line: print(line, flush=True),
    )
    before, after = summary["before"], summary["after"]
    print(
        f"held-out {summary['target']} ({summary['held_out']} images): "
        f"SSIM {before['ssim']:.4f} -> {after['ssim']:.4f}, "
        f"PSNR {before['psnr']:.2f} -> {after['psnr']:.2f} dB ({summary['steps']} steps, {summary['seconds']:.1f} s)"
    )
    if "real_frames" in summary:
        real = summary["real_frames"]
        print(
            f"{real['count']} real frames: SSIM {real['before']['ssim']:.4f} -> {real['after']['ssim']:.4f}, "
            f"PSNR {real['before']['psnr']:.2f} -> {real['after']['psnr']:.2f} dB"
        )
    print(f"-> {out} (autoencoder.safetensors, quantizer.safetensors, adapt.json, before_after.png)")
    return 0


def cmd_evaluate_cross_sensor(args: argparse.Namespace) -> int:
    from .evaluation import evaluate_cross_sensor

    out = Path(args.out)
    evaluate_cross_sensor(
        args.run,
        args.host,
        out,
        target=args.target,
        seeds=args.seeds,
        steps=args.steps,
        shots=args.shots,
        ratios=args.ratios,
        main_shots=args.main_shots,
        main_ratio=args.main_ratio,
        everything=args.everything,
        eval_images=args.eval_images,
        variants=args.variants,
        held_out_variants=args.held_out_variants,
        images=args.images,
        clusterers=args.clusterers,
        real_family=None if args.real == "none" else args.real,
        real_shots=args.real_shots,
        report=lambda line: print(line, flush=True),
    )
    print((out / "cross_sensor.md").read_text())
    print(f"-> {out} (cross_sensor.json, cross_sensor.md, cross_sensor.png)")
    return 0


def cmd_evaluate_fewshot(args: argparse.Namespace) -> int:
    from .fewshot import evaluate_fewshot

    out = Path(args.out)
    evaluate_fewshot(
        args.run,
        args.host,
        out,
        target=args.target,
        seeds=args.seeds,
        counts=args.n,
        ratio=args.ratio,
        steps=args.steps,
        scratch_steps=args.scratch_steps,
        eval_images=args.eval_images,
        families=args.families,
        overwrite=args.overwrite,
        report=lambda line: print(line, flush=True),
    )
    print((out / "fewshot.md").read_text())
    print(f"-> {out} (fewshot.json, fewshot.md, fewshot.png; the trained arms' tokenizers in seed<S>/<arm>-<N>/)")
    return 0


def cmd_evaluate_mix_ratio(args: argparse.Namespace) -> int:
    from .ratio import evaluate_mix_ratio

    out = Path(args.out)
    evaluate_mix_ratio(
        args.run,
        args.host,
        out,
        target=args.target,
        seeds=args.seeds,
        shots=args.shots,
        ratios=args.ratios,
        steps=args.steps,
        all_images=args.all_images,
        eval_images=args.eval_images,
        families=args.families,
        cost_controls=args.cost_controls,
        overwrite=args.overwrite,
        report=lambda line: print(line, flush=True),
    )
    print((out / "mix_ratio.md").read_text())
    print(f"-> {out} (mix_ratio.json, mix_ratio.md, mix_ratio.png; each arm's tokenizer in seed<S>/<arm>/)")
    return 0

"""``vqtouch evaluate cross-sensor``: the cross-sensor experiment in one command.

Three parts, each over several seeds, written as ``cross_sensor.json``, ``cross_sensor.md`` (tables)
and ``cross_sensor.png`` (figures):

1. **Family recovery.**  Every registered sensor family with ``variants`` random environmental
   variants each (illumination, colour gain, drift, response, wear, damage, noise, misalignment:
   :func:`vqtouch.sensors.environment_variant`, new variant seeds per evaluation seed) is clustered
   from the tokenizer's features by each clusterer; the adjusted Rand index against the true
   families, and the assignment accuracy of ``held_out_variants`` further variants per family.
2. **Transfer to an unseen sensor**, every arm fine-tuned for the same steps from the family
   tokenizer: (a) zero-shot (the family tokenizer as it is), (b) the shots alone, (c) the shots
   mixed 1:ratio with family data, (d) everything (``everything`` target images mixed 1:1 with
   family data); (c) at every shot count and ratio asked.  SSIM, PSNR, ``fd_effnetlite0`` and
   codebook usage on held-out target images.
3. **Real frames as the unseen sensor**: taxim's captured GelSight Mini frames (arms a-c; there
   are not enough frames for (d)), when the tokenizer works at a size the frames allow.

Plus the **cost**: arm (c)'s adaptation wall time against training a fresh tokenizer (the run's
config and steps) on everything, measured in the same process.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch

from vqtouch.plugins.runtime.outputs import output_folder
from vqtouch.core import ConfigError, PluginHost
from vqtouch.plugins.evaluation.records import markdown_table, mean_spread
from vqtouch.core.image_size import ImageSize, image_hw, size_text

from .adapt import AdaptSettings, adapt_tokenizer, reconstruction_scores
from .adapt_images import family_images, target_images
from .families import SensorFamilies, family_sensor_specs, fit_families, sensor_images
from .scratch import train_fresh_tokenizer

METRICS = ("ssim", "psnr", "fd_effnetlite0")
TABLE_COLUMNS = ("ssim", "psnr", "fd_effnetlite0", "codebook_usage", "family_ssim", "family_psnr", "seconds")


def _family_of(source: str) -> str:
    """The registered family name of a rendered sensor's source JSON."""
    return json.loads(source)["name"]


def family_recovery(
    tokenizer: Any,
    host: PluginHost,
    *,
    seed: int,
    variants: int,
    held_out_variants: int,
    images: int,
    image_size: ImageSize,
    clusterers: list[str],
    tokenizer_source: str,
) -> tuple[list[dict], SensorFamilies]:
    """One seed of part 1: per clusterer, the families found, the ARI and the held-out assignment
    accuracy.  Returns the rows and the first clusterer's families (used by the transfer arms)."""
    from sklearn.metrics import adjusted_rand_score

    specs = family_sensor_specs(host, variants, first_seed=1000 + 100 * seed)
    unseen = [
        spec
        for spec in family_sensor_specs(host, held_out_variants, first_seed=1050 + 100 * seed)
        if "variant" in json.loads(spec)
    ]
    rows, first = [], None
    for name in clusterers:
        families = fit_families(
            tokenizer,
            specs,
            host,
            clusterer=host.build("clusterer", {"name": name, "seed": seed}),
            images=images,
            image_size=image_size,
            seed=seed,
            tokenizer_source=tokenizer_source,
            report=lambda line: None,
        )
        summary = families.summary
        truth = [_family_of(sensor["source"]) for sensor in summary["sensors"]]
        found = [summary["sensor_family"][sensor["name"]] for sensor in summary["sensors"]]
        majority = {
            family: max(set(members), key=members.count)
            for family in set(found)
            for members in [[t for t, f in zip(truth, found) if f == family]]
        }
        correct = refused = 0
        for spec in unseen:
            sensor = sensor_images(spec, host, count=images, image_size=image_size, seed=seed + 1)
            assigned, _ = families.unseen(tokenizer, sensor.name, sensor.images)
            refused += assigned["refused"]
            correct += (not assigned["refused"]) and majority[assigned["family"]] == _family_of(spec)
        rows.append(
            {
                "clusterer": name,
                "seed": seed,
                "sensors": len(specs),
                "true_families": len(set(truth)),
                "families": len(summary["families"]),
                "ari": round(adjusted_rand_score(truth, found), 4),
                "assignment_accuracy": round(correct / len(unseen), 4),
                "refused": refused,
                "held_out_sensors": len(unseen),
            }
        )
        first = first or families
    return rows, first


def _arm_settings(shots: int, ratio: float, steps: int, eval_images: int, seed: int, **extra: Any) -> AdaptSettings:
    return AdaptSettings(
        shots=shots, ratio=ratio, steps=steps, eval_images=eval_images, seed=seed, metrics=METRICS, **extra
    )


def _arm_row(arm: str, summary: dict[str, Any], *, zero_shot: bool = False) -> dict[str, Any]:
    when = "before" if zero_shot else "after"
    scores, family = summary[when], summary["family_held_out"][when]
    return {
        "arm": arm,
        "shots": 0 if zero_shot else summary["shots"],
        "ratio": None if zero_shot else summary["ratio"],
        "held_out": summary["held_out"],
        **{key: scores.get(key) for key in METRICS},
        "codebook_usage": scores.get("codebook_usage"),
        "family": summary["family"],
        "family_ssim": family["ssim"],
        "family_psnr": family["psnr"],
        "seconds": 0.0 if zero_shot else summary["seconds"],
    }


def transfer_arms(
    run: Any,
    target: str,
    families: SensorFamilies,
    host: PluginHost,
    out: Path,
    *,
    seed: int,
    steps: int,
    shots: list[int],
    ratios: list[float],
    main_shots: int,
    main_ratio: float,
    everything: int,
    eval_images: int,
    family: int | None = None,
) -> list[dict[str, Any]]:
    """One seed of part 2 (or 3, with a folder target): every arm's held-out scores."""
    rows = []

    def arm(name: str, shot_count: int, ratio: float) -> dict[str, Any]:
        settings = _arm_settings(shot_count, ratio, steps, eval_images, seed, family=family)
        return adapt_tokenizer(
            run,
            target,
            families,
            host,
            out / f"seed{seed}" / f"{name}-{shot_count}-{ratio:g}",
            settings,
            overwrite=True,
            report=lambda line: None,
        )

    first = arm("b", shots[0], 0.0)
    rows.append(_arm_row("a: zero-shot", first, zero_shot=True))
    rows.append(_arm_row("b: shots alone", first))
    for count in shots[1:]:
        rows.append(_arm_row("b: shots alone", arm("b", count, 0.0)))
    for count in shots:
        rows.append(_arm_row("c: mixed", arm("c", count, main_ratio)))
    for ratio in ratios:
        if ratio != main_ratio:
            rows.append(_arm_row("c: mixed", arm("c", main_shots, ratio)))
    if everything:
        rows.append(_arm_row("d: everything", arm("d", everything, 1.0)))
    return rows


def scratch_cost(
    run: Any,
    target: str,
    families: SensorFamilies,
    host: PluginHost,
    *,
    seed: int,
    everything: int,
    eval_images: int,
    family: int,
) -> dict[str, Any]:
    """Train a fresh tokenizer (the run's config and steps) on everything; its wall time and scores."""
    image_size = families.summary["image_size"]
    _, source, target_N, held_out = target_images(
        target, host, shots=everything, eval_images=eval_images, image_size=image_size, seed=seed
    )
    family_N, _ = family_images(
        families, family, host, count=everything, image_size=image_size, seed=seed, exclude=source
    )
    tokenizer, trained = train_fresh_tokenizer(run, torch.cat([target_N, family_N]), host, seed=seed)
    scores = reconstruction_scores(tokenizer, held_out, host, metrics=METRICS)
    return {
        "arm": "fresh tokenizer on everything",
        "shots": everything,
        "ratio": 1.0,
        "held_out": len(held_out),
        **{key: scores.get(key) for key in METRICS},
        "codebook_usage": scores.get("codebook_usage"),
        "steps": trained["steps"],
        "seconds": trained["seconds"],
    }


def plot_transfer(transfer: list[dict[str, Any]], path: Path, title: str) -> None:
    """SSIM against shots (arms b and c, with a and d as lines) and against the mix ratio."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(10, 4), dpi=110)
    FigureCanvasAgg(figure)
    by_shots, by_ratio = figure.add_subplot(1, 2, 1), figure.add_subplot(1, 2, 2)
    main_ratio = max(
        (row["ratio"] for row in transfer if row["arm"] == "c: mixed"),
        key=lambda r: sum(1 for row in transfer if row["arm"] == "c: mixed" and row["ratio"] == r),
    )
    for arm, marker in (("b: shots alone", "o"), ("c: mixed", "s")):
        points = sorted(
            (row["shots"], row["ssim"], row.get("ssim_std", 0))
            for row in transfer
            if row["arm"] == arm and (arm != "c: mixed" or row["ratio"] == main_ratio)
        )
        if points:
            xs, ys, errors = zip(*points)
            label = arm if arm != "c: mixed" else f"c: mixed 1:{main_ratio:g}"
            by_shots.errorbar(xs, ys, yerr=errors, marker=marker, capsize=3, label=label)
    for arm, style in (("a: zero-shot", "--"), ("d: everything", ":")):
        for row in transfer:
            if row["arm"] == arm:
                by_shots.axhline(row["ssim"], linestyle=style, color="grey", label=arm)
    by_shots.set_xscale("log")
    by_shots.set_xlabel("unseen-sensor shots")
    by_shots.set_ylabel("held-out SSIM")
    by_shots.legend(fontsize=8)
    by_shots.grid(alpha=0.3)
    mixed = sorted(
        {row["shots"] for row in transfer if row["arm"] == "c: mixed"},
        key=lambda s: -sum(1 for row in transfer if row["arm"] == "c: mixed" and row["shots"] == s),
    )
    if mixed:
        points = sorted(
            (row["ratio"], row["ssim"], row.get("ssim_std", 0))
            for row in transfer
            if row["arm"] == "c: mixed" and row["shots"] == mixed[0]
        )
        xs, ys, errors = zip(*points)
        by_ratio.errorbar(xs, ys, yerr=errors, marker="s", capsize=3)
        by_ratio.set_xlabel(f"family images per shot ({mixed[0]} shots)")
    by_ratio.set_ylabel("held-out SSIM")
    by_ratio.grid(alpha=0.3)
    figure.suptitle(title, fontsize=9)
    figure.tight_layout()
    figure.savefig(path)


def real_frames_folder(host: PluginHost, family: str, image_size: ImageSize, folder: Path) -> Path | None:
    """Write the captured frames ``family`` ships (e.g. taxim's GelSight Mini) as PNGs; None without any."""
    from vqtouch.plugins.utils.images import save_png

    frames = host.build("sensor_family", family).reference_frames(*image_hw(image_size))
    if frames is None:
        return None
    folder.mkdir(parents=True, exist_ok=True)
    for index, frame in enumerate(frames):
        save_png(frame, folder / f"frame_{index:03d}.png")
    return folder


def evaluate_cross_sensor(
    run: Any,
    host: PluginHost,
    out: Path,
    *,
    target: str,
    seeds: list[int],
    steps: int,
    shots: list[int],
    ratios: list[float],
    main_shots: int,
    main_ratio: float,
    everything: int,
    eval_images: int,
    variants: int,
    held_out_variants: int,
    images: int,
    clusterers: list[str],
    real_family: str | None,
    real_shots: list[int],
    report: Any = print,
) -> dict[str, Any]:
    """Run the three parts and the cost (see the module docstring); write the JSON, markdown and PNG."""
    from vqtouch.plugins.tokenizer import load_tokenizer

    tokenizer, folder = load_tokenizer(run, host)
    image_size = tokenizer.autoencoder.vqtouch_spec.context.image_size
    if main_shots not in shots:
        raise ConfigError(f"--main-shots {main_shots} must be one of --shots {shots}")
    output_folder(out)
    real, usable = _real_target(host, real_family, real_shots, image_size, out)
    recovery, transfer, real_rows, costs = [], [], [], []
    for seed in seeds:
        rows, families = _recover_families(
            tokenizer, folder, host, seed, variants, held_out_variants, images, image_size, clusterers, report
        )
        recovery += rows
        seed_rows = transfer_arms(
            run,
            target,
            families,
            host,
            out / "arms",
            seed=seed,
            steps=steps,
            shots=shots,
            ratios=ratios,
            main_shots=main_shots,
            main_ratio=main_ratio,
            everything=everything,
            eval_images=eval_images,
        )
        transfer += [{**row, "seed": seed} for row in seed_rows]
        report(
            f"seed {seed}: transfer "
            + ", ".join(f"{r['arm'][0]}{r['shots']}/{r['ratio']} {r['ssim']}" for r in seed_rows)
        )
        adapted = _main_arm(seed_rows, main_shots, main_ratio)
        if everything and (Path(run) / "config.json").is_file():
            costs.append(_cost_row(run, target, families, host, seed, everything, eval_images, adapted, report))
        if real is not None:
            real_rows += _real_frame_rows(tokenizer, run, real, usable, families, host, out, seed, steps, main_ratio)
    result = _cross_sensor_result(
        folder, target, seeds, steps, image_size, recovery, transfer, real_family, real_rows, costs
    )
    _write_cross_sensor(out, result, target, steps, len(seeds))
    return result


def _real_target(
    host: PluginHost, real_family: str | None, real_shots: list[int], image_size: ImageSize, out: Path
) -> tuple[Any, list[int]]:
    """The captured frames of ``real_family`` as an unseen sensor (None without any) and the shot counts
    they leave held-out frames for."""
    real, usable = None, []
    if real_family is not None:  # written and read once: every seed adapts to the same frames
        frames = real_frames_folder(host, real_family, image_size, out / f"real_{real_family}")
        if frames is not None:
            real = sensor_images(str(frames), host, count=len(list(frames.iterdir())), image_size=image_size)
            usable = [count for count in real_shots if count < len(real.images)]
    return real, usable


def _recover_families(
    tokenizer: Any,
    folder: Path,
    host: PluginHost,
    seed: int,
    variants: int,
    held_out_variants: int,
    images: int,
    image_size: ImageSize,
    clusterers: list[str],
    report: Any,
) -> tuple[list[dict[str, Any]], SensorFamilies]:
    """One seed of part 1, reported: its rows and the families the transfer arms adapt from."""
    rows, families = family_recovery(
        tokenizer,
        host,
        seed=seed,
        variants=variants,
        held_out_variants=held_out_variants,
        images=images,
        image_size=image_size,
        clusterers=clusterers,
        tokenizer_source=str(folder),
    )
    report(f"seed {seed}: family recovery " + ", ".join(f"{r['clusterer']} ARI {r['ari']}" for r in rows))
    return rows, families


def _main_arm(seed_rows: list[dict[str, Any]], main_shots: int, main_ratio: float) -> dict[str, Any]:
    """The mixed arm at the main shot count and ratio: the adaptation the cost compares."""
    return next(
        row
        for row in seed_rows
        if row["arm"] == "c: mixed" and row["shots"] == main_shots and row["ratio"] == main_ratio
    )


def _cost_row(
    run: Any,
    target: str,
    families: SensorFamilies,
    host: PluginHost,
    seed: int,
    everything: int,
    eval_images: int,
    adapted: dict[str, Any],
    report: Any,
) -> dict[str, Any]:
    """One seed of the cost, reported: the adaptation's wall time against a fresh tokenizer's."""
    scratch = scratch_cost(
        run,
        target,
        families,
        host,
        seed=seed,
        everything=everything,
        eval_images=eval_images,
        family=adapted["family"],
    )
    row = {
        "seed": seed,
        "adaptation_seconds": adapted["seconds"],
        "scratch_seconds": scratch["seconds"],
        "scratch_steps": scratch["steps"],
        "ratio": float(f"{adapted['seconds'] / scratch['seconds']:.4g}"),
        "scratch_ssim": scratch["ssim"],
        "scratch_psnr": scratch["psnr"],
        "adapted_ssim": adapted["ssim"],
    }
    report(f"seed {seed}: adaptation {adapted['seconds']} s vs fresh training {scratch['seconds']} s")
    return row


def _real_frame_rows(
    tokenizer: Any,
    run: Any,
    real: Any,
    usable: list[int],
    families: SensorFamilies,
    host: PluginHost,
    out: Path,
    seed: int,
    steps: int,
    main_ratio: float,
) -> list[dict[str, Any]]:
    """One seed of part 3: the arms adapted to the captured frames, from the family they are nearest to."""
    assigned, _ = families.unseen(tokenizer, real.name, real.images)
    nearest = assigned["nearest_family"]
    rows = transfer_arms(
        run,
        real.source,
        families,
        host,
        out / "real_arms",
        seed=seed,
        steps=steps,
        shots=usable,
        ratios=[main_ratio],
        main_shots=usable[-1],
        main_ratio=main_ratio,
        everything=0,
        eval_images=len(real.images) - max(usable),
        family=nearest,
    )
    return [
        {
            **row,
            "seed": seed,
            "assigned_family": assigned["family"],
            "nearest_family": nearest,
            "refused": assigned["refused"],
            "margin": assigned["margin"],
        }
        for row in rows
    ]


def _cross_sensor_result(
    folder: Path,
    target: str,
    seeds: list[int],
    steps: int,
    image_size: ImageSize,
    recovery: list[dict[str, Any]],
    transfer: list[dict[str, Any]],
    real_family: str | None,
    real_rows: list[dict[str, Any]],
    costs: list[dict[str, Any]],
) -> dict[str, Any]:
    """What ``cross_sensor.json`` holds: every part's rows and their mean and spread over the seeds."""
    group = ("arm", "shots", "ratio")
    return {
        "tokenizer": str(folder),
        "target": target,
        "seeds": seeds,
        "steps": steps,
        "image_size": image_size,
        "family_recovery": {
            "rows": recovery,
            "summary": mean_spread(recovery, ("ari", "assignment_accuracy", "families", "refused"), ("clusterer",)),
        },
        "transfer": {"rows": transfer, "summary": mean_spread(transfer, TABLE_COLUMNS, group)},
        "real_frames": {
            "family": real_family,
            "rows": real_rows,
            "summary": mean_spread(real_rows, TABLE_COLUMNS, group),
        },
        "cost": {
            "rows": costs,
            "summary": mean_spread(
                costs, ("adaptation_seconds", "scratch_seconds", "ratio", "scratch_ssim", "adapted_ssim"), ()
            ),
        },
    }


def _write_cross_sensor(out: Path, result: dict[str, Any], target: str, steps: int, seed_count: int) -> None:
    """Write ``cross_sensor.json``, its markdown tables and the transfer figure into ``out``."""
    (out / "cross_sensor.json").write_text(json.dumps(result, indent=2) + "\n")
    (out / "cross_sensor.md").write_text(render_markdown(result) + "\n")
    plot_transfer(
        result["transfer"]["summary"],
        out / "cross_sensor.png",
        f"transfer to {json.loads(target)['name'] if target.startswith('{') else target} "
        f"({steps} steps per arm, {seed_count} seeds)",
    )


def render_markdown(result: dict[str, Any]) -> str:
    """The tables of ``cross_sensor.json`` for people."""
    seeds = len(result["seeds"])
    lines = [
        f"# Cross-sensor evaluation ({seeds} seeds: mean ± std)",
        "",
        f"Tokenizer `{result['tokenizer']}`, {size_text(result['image_size'])} px; every arm fine-tunes "
        f"{result['steps']} steps.  `ssim` to `codebook_usage`: held-out images of the unseen sensor; "
        "`family_ssim`, `family_psnr`: held-out images of the family's members (what an adaptation keeps of "
        "the family); `seconds`: fine-tuning wall time.",
        "",
        "## Family recovery",
        "",
    ]
    lines += markdown_table(
        result["family_recovery"]["summary"], ("clusterer",), ("ari", "assignment_accuracy", "families", "refused")
    )
    lines += ["", f"## Transfer to `{result['target']}`", ""]
    lines += markdown_table(result["transfer"]["summary"], ("arm", "shots", "ratio"), TABLE_COLUMNS)
    if result["real_frames"]["rows"]:
        rows = result["real_frames"]["rows"]
        refused = sum(row["refused"] for row in rows if row["arm"].startswith("a"))
        lines += [
            "",
            f"## Real {result['real_frames']['family']} frames as the unseen sensor",
            "",
            f"Assigned family (nearest): {sorted({row['nearest_family'] for row in rows})}; refused by the "
            f"threshold in {refused} of {seeds} seeds; every arm adapts from the nearest family.",
            "",
        ]
        lines += markdown_table(result["real_frames"]["summary"], ("arm", "shots", "ratio"), TABLE_COLUMNS)
    if result["cost"]["rows"]:
        lines += ["", "## Cost", ""]
        lines += markdown_table(
            result["cost"]["summary"],
            (),
            ("adaptation_seconds", "scratch_seconds", "ratio", "adapted_ssim", "scratch_ssim"),
        )
    return "\n".join(lines)

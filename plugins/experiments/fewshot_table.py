"""``vqtouch evaluate fewshot-generation``: ``vqtouch fewshot``
(:func:`~vqtouch.plugins.experiments.fewshot_generation.fewshot_generation`) once per seed and ratio,
an interrupted table resumed from the arms it finished, and the scores as mean ± std over the seeds."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any, Sequence

from vqtouch.core import ConfigError, PluginHost, atomic_write
from vqtouch.plugins.evaluation.records import markdown_table
from vqtouch.plugins.utils.files import FileModel, read_model

from .fewshot_generation import fewshot_generation, fewshot_options, new_sensor_images, render_markdown
from .fewshot_scoring import CLASSIFIER_TEXT, RECONSTRUCTED, SCORE_HEADERS, SCORE_KEYS, sample_and_score


class FewshotRecord(FileModel):
    """What is read back of a ``fewshot.json``: the settings it ran with and its score rows."""

    images: str
    shots: int
    ratio: float
    seed: int
    scores: list[dict[str, Any]]


def arm_name(arm: str, ratio: float) -> str:
    """An arm's name in the seeds table: the fine-tuned arm by its ratio (``few-shot 1:5``; ``shots
    alone`` at ratio 0), the comparisons as they are."""
    if arm == RECONSTRUCTED:  # the ceiling depends on the adapted tokenizer, so on the ratio
        return f"new sensor, reconstructed by the {'shots-alone' if ratio == 0 else f'1:{ratio:g}'} tokenizer (ceiling)"
    if arm != "few-shot":
        return arm
    return "shots alone" if ratio == 0 else f"few-shot 1:{ratio:g}"


def evaluate_fewshot_generation(
    family_run: str,
    images: str,
    out: Path,
    host: PluginHost,
    *,
    seeds: Sequence[int],
    ratios: Sequence[float],
    report: Any = print,
    overwrite: bool = False,
    **options: Any,
) -> dict[str, Any]:
    """:func:`~vqtouch.plugins.experiments.fewshot_generation.fewshot_generation` once per seed and
    ratio into ``out/seed<S>/ratio<R>/`` (a folder that already holds a finished run with the same
    images, shots, ratio and seed is read, not run again: an interrupted table resumes; one with other
    settings is refused unless ``overwrite``, which runs every arm again), then ``fd_effnetlite0`` per
    conditioner and arm as mean ± std over the seeds: ``fewshot_generation.json`` and
    ``fewshot_generation.md``.  The zero-shot, copied-shots and
    background rows of a seed are the same at every ratio (same held-out images and conditions); the
    first ratio's are kept."""
    from vqtouch.plugins.evaluation.records import ExperimentRecord, mean_spread

    record = ExperimentRecord("fewshot_generation", out, seeds, overwrite=overwrite)
    rows: list[dict[str, Any]] = []
    for seed in record.seeds:
        for position, ratio in enumerate(ratios):
            folder = Path(out) / f"seed{seed}" / f"ratio{ratio:g}"
            settings = {"images": images, "shots": options.get("shots", 50), "ratio": ratio, "seed": seed}
            previous = None if overwrite else finished_arm(folder, settings)
            if previous is not None:
                report(f"seed {seed}, ratio {ratio:g}: read {folder / 'fewshot.json'}")
                result = previous
                if ("paired_truth" not in result or "classifier" not in result) and result["scores"]:
                    report("    scored before the paired scores existed: drawing its samples again to score them")
                    result = score_again(folder, family_run, host, report=report, **options)
            else:
                report(f"seed {seed}, ratio {ratio:g} -> {folder}")
                result = fewshot_generation(
                    family_run, images, folder, host, ratio=ratio, seed=seed, overwrite=True, report=report, **options
                )
            for row in result["scores"]:
                if row["arm"] in ("few-shot", RECONSTRUCTED) or position == 0:
                    rows.append({**row, "arm": arm_name(row["arm"], ratio), "seed": seed})
    table = mean_spread(rows, list(SCORE_KEYS), ["conditioner", "arm"])
    result = {"family_run": family_run, "images": images, "ratios": list(ratios), "rows": rows, "summary": table}
    lines = [
        f"# Few-shot generation: {images}",
        "",
        f"Mean ± std over seeds {', '.join(map(str, record.seeds))}.  fd_effnetlite0 (lower is better): each "
        "conditioner's samples against as many held-out images of the new sensor (never the shots).  Where the "
        "sensor renders the family's scenes (paired): contact PSNR against its image of each condition's own "
        f"contact, and {CLASSIFIER_TEXT}",
        "",
        *markdown_table(table, ["conditioner", "arm"], list(SCORE_KEYS), SCORE_HEADERS),
    ]
    record.write(result, lines)
    return result


def finished_arm(folder: Path, settings: dict[str, Any]) -> dict[str, Any] | None:
    """The ``fewshot.json`` of an arm finished with ``settings`` (None when there is none); a finished arm
    with other settings is refused in one line: it is replaced only with ``--overwrite``."""
    done = folder / "fewshot.json"
    if not done.is_file():
        return None
    previous = read_model(done, FewshotRecord).model_dump()
    differing = {key: previous.get(key) for key, value in settings.items() if previous.get(key) != value}
    if differing:
        said = ", ".join(f"{key} {previous.get(key)!r} (now {settings[key]!r})" for key in differing)
        raise ConfigError(
            f"{folder} holds a finished arm with other settings: {said}; pass --overwrite to run every arm "
            "again, or choose another --out"
        )
    return previous


def score_again(
    folder: Path,
    family_run: str,
    host: PluginHost,
    *,
    eval_images: int = 64,
    samples: int = 32,
    feature_size: int = 224,
    report: Any = print,
    **_: Any,
) -> dict[str, Any]:
    """Steps 3 to 5 again on a finished ``vqtouch fewshot`` output (its generator run is kept): the same
    draws, scored with what this version scores; rewrites its ``fewshot.json`` and ``fewshot.md``."""
    from vqtouch.plugins.generator import load_pipeline

    result = read_model(folder / "fewshot.json", FewshotRecord).model_dump()
    images, shots, seed = result["images"], result["shots"], result["seed"]
    family_pipe = load_pipeline(family_run, host=host)
    name, shots_N3HW, held_out_M3HW, background_3HW, _ = new_sensor_images(
        images, host, shots=shots, eval_images=eval_images, image_size=family_pipe.config.data.image_size, seed=seed
    )
    result |= sample_and_score(
        load_pipeline(folder / "generator", host=host),
        family_pipe,
        images,
        name,
        folder,
        host,
        held_out_M3HW=held_out_M3HW,
        shots_N3HW=shots_N3HW,
        background_3HW=background_3HW,
        samples=samples,
        seed=seed,
        feature_size=feature_size,
        report=report,
    )
    atomic_write(folder / "fewshot.json", lambda tmp: tmp.write_text(json.dumps(result, indent=2, default=str) + "\n"))
    atomic_write(folder / "fewshot.md", lambda tmp: tmp.write_text("\n".join(render_markdown(result)) + "\n"))
    return result


def _evaluate_fewshot_generation_command(args: argparse.Namespace) -> int:
    out = Path(args.out)
    evaluate_fewshot_generation(
        args.run,
        args.images,
        out,
        args.host,
        seeds=args.seeds,
        ratios=args.ratios,
        report=lambda line: print(line, flush=True),
        overwrite=args.overwrite,
        **fewshot_options(args),
    )
    print((out / "fewshot_generation.md").read_text())
    print(f"-> {out} (fewshot_generation.json, fewshot_generation.md, seed*/ratio*/)")
    return 0

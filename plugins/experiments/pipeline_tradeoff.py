"""``vqtouch evaluate tradeoff``: the whole pipeline's speed/accuracy trade, tokenizer knobs and
generator knobs in one table, measured in one process.

::

    vqtouch evaluate tradeoff --out runs/tradeoff                      # label-to-touch, scaled for a CPU
    vqtouch evaluate tradeoff --out runs/tradeoff --quick              # fewer steps and knobs (~15 min)
    vqtouch evaluate tradeoff reconstruction --out DIR --knobs deformable codebook=128,2048 precision
    vqtouch evaluate tradeoff --out DIR --set 'data.dataset={"name": "image_folder", "root": "data/frames"}'

The baseline is the scene's config (``SCENE``/``--config``/``--set``; default ``label-to-touch``),
scaled down like ``vqtouch demo`` unless ``--full``, every training shortened to
``--tokenizer-steps`` / ``--generator-steps``.  For every seed:

1. **Tokenizer knobs.**  The baseline tokenizer and one tokenizer per knob value (one knob changed
   at a time: deformable layers on/off, i.e. ``dm_vqgan`` against ``vqgan``; codebook size;
   resolution; training precision; downsampling factor f) train the same number of steps through
   the ``tokenizer`` stage (:func:`vqtouch.core.run_stage`, what ``vqtouch train tokenizer`` runs),
   each in its own run folder, and are scored by that stage on the held-out split: SSIM, PSNR and
   their contact-region scores, next to the same scores of the sensor's no-contact image
   (``background_*``: what a tokenizer that draws only the background gets).  Then their costs are
   timed in interleaved rounds (round 1 of every tokenizer, then round 2, ...; the median is kept):
   ``--timing-steps`` training steps through the trainer (seconds per step) and an encode + decode
   of the held-out images (images per second).  The baseline is timed first AND last in every
   round; the last timing's ratio to the first is the machine's drift during a round.
2. **Generator knobs.**  A generator trains (``generator`` stage) on the baseline tokenizer's codes
   in the baseline's run; then ``vqtouch tradeoff generator``'s functions
   (:mod:`vqtouch.plugins.generator.tradeoff`) time and score every sampling setting (steps,
   sampler, guidance, sampling precision; one at a time around the configured one, the configured
   one repeated last) on the held-out conditions.  The cost of a generated image is the whole
   pipeline's: condition encoding, sampling and decoding by the tokenizer.

Time (2-core CPU, scaled scene, a machine shared with other jobs, ``--threads 1``): one seed of
the default knobs took 12.8 min at 4 tokenizer steps and 15.1 min at 12, i.e. about 17 s per
tokenizer step for all 7 tokenizers and 12 min of scoring, timing and generation; the default
(150 steps, 3 seeds) extrapolates to 2 h 45 min there.  ``--quick`` (40 steps, 5 tokenizers, 5
sampling settings) took 12 min for one seed there, so about 37 min for three.  A quiet machine is
about 3x faster (VQGAN's step: 1.6 s there, 0.49 s in docs/results.md).  Two OpenMP threads per
process on a shared CPU spin against each other: give ``--threads 1`` there.

Every cost is also given relative to the baseline timed in the same seed's process (``x base``),
then averaged over the seeds.  Writes ``tradeoff.json`` (every per-seed row, the mean ± std
summary with the Pareto fronts, the knobs, the baseline config and the provenance),
``tradeoff.md`` (the one table) and ``tradeoff.png`` (Pareto plots: tokenizer training cost,
tokenizer inference cost and generation cost, each against the contact-region SSIM).  A setting
is on a front when no other setting of its part is at least as cheap and at least as good on the
contact region, and strictly better in one (:func:`~vqtouch.plugins.generator.tradeoff.pareto_front`);
claims of "better" are made on the contact region, never on the whole-image scores.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import re
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from vqtouch.core import Assembly, PluginHost
from vqtouch.plugins.utils.seeding import resolve_device
from vqtouch.plugins.runtime.execution import run_stage
from vqtouch.plugins.runtime.run_dir import RunDir
from vqtouch.plugins.cli.app import config_from_args, stage_failure
from vqtouch.plugins.evaluation.records import ExperimentRecord
from vqtouch.plugins.training.trainer import Trainer
from vqtouch.plugins.utils.splits import experiment_split
from vqtouch.plugins.tokenizer import load_tokenizer, reconstruct_all, tokenizer_task

from .pipeline_tradeoff_configs import (
    DEFAULT_SCENE,
    baseline_config,
    baseline_text,
    check_sampling_values,
    generator_base,
    parse_knobs,
    scaled_config,
    variant_config,
)
from .pipeline_tradeoff_knobs import KNOBS, Knob, known_knobs  # noqa: F401 (their old home)
from .pipeline_tradeoff_plugin import QUICK, QUICK_KNOBS, STANDARD
from .pipeline_tradeoff_report import DRIFT, QUALITY_KEYS, plot_tradeoff, render_markdown, summarize

#: At most this many held-out images are encoded and decoded per inference timing.
TIMED_IMAGES = 64


# -- training and timing --------------------------------------------------------------------------


def train_tokenizer_run(config: Any, host: PluginHost, folder: Path, argv: list[str]) -> tuple[Path, float]:
    """Train ``config``'s tokenizer through :func:`run_stage` in a new run ``folder`` (replacing an
    earlier run there; a folder that holds no run is refused); the folder and the stage's seconds."""
    run = RunDir.create(config, argv=argv, host=host, path=folder, overwrite=True)
    with run:
        outcome = run_stage("tokenizer", Assembly(config, host), run)
    if outcome.status != "ran":
        raise stage_failure(outcome)
    return run.path, outcome.seconds


class TokenizerTimer:
    """One trained tokenizer's costs: seconds per training step (the run's objective, optimiser,
    precision and batch through the trainer) and encode + decode seconds per held-out image."""

    def __init__(self, config: Any, run: Path, host: PluginHost, steps: int) -> None:

        self.config, self.host, self.steps = config, host, steps
        self.device = resolve_device(config.device)
        self.tokenizer, _ = load_tokenizer(run, host, device=str(self.device))
        assembly = Assembly(config, host)
        dataset = assembly.component("data.dataset")
        self.train_set, held_out = experiment_split(dataset, config.data, config.seed)
        count = min(len(held_out), TIMED_IMAGES)
        self.images_B3HW = torch.stack([held_out[index]["tactile"] for index in range(count)]).to(self.device)
        section = config.tokenizer
        discriminator = (
            assembly.component("tokenizer.discriminator")
            if section.discriminator is not None and section.loss.adversarial_weight > 0
            else None
        )
        self.task = tokenizer_task(self.tokenizer, section.loss, self.device, discriminator)
        self.train_config = section.train.model_copy(
            update={"steps": steps, "checkpoint_every": steps, "keep_best": False}
        )

    def training_seconds_per_step(self) -> float:
        """Seconds per step of ``steps`` training steps (a fresh optimiser; the weights go on training,
        which does not change what a step costs)."""
        from vqtouch.plugins.generator import synchronize

        trainer = Trainer(
            self.task,
            self.train_set,
            self.train_config,
            batch_size=self.config.data.batch_size,
            seed=self.config.seed,
            device=self.device,
            checkpoint_dir=None,
            num_workers=self.config.data.num_workers,
            host=self.host,
            stage="timing",
        )
        synchronize(self.device)
        tic = time.perf_counter()
        trainer.fit()
        synchronize(self.device)
        return (time.perf_counter() - tic) / self.steps

    def seconds_per_image(self) -> float:
        """Seconds to encode and decode one held-out image (batches of the run's batch size)."""
        from vqtouch.plugins.generator import synchronize

        self.tokenizer.eval()
        synchronize(self.device)
        tic = time.perf_counter()
        reconstruct_all(self.tokenizer, self.images_B3HW, batch_size=self.config.data.batch_size)
        synchronize(self.device)
        return (time.perf_counter() - tic) / len(self.images_B3HW)


def time_tokenizers(
    timers: list[TokenizerTimer], rounds: int, report: Callable[[str], None]
) -> list[tuple[float, float]]:
    """(training seconds per step, seconds per image) of each timer, the median of ``rounds``
    interleaved rounds, and last the baseline's (``timers[0]``) second timing of every round.  One
    untimed round first pays the first-call costs (allocation, the data's first renders)."""
    order = [*range(len(timers)), 0]
    for timer in timers:
        timer.training_seconds_per_step()
        timer.seconds_per_image()
    training: list[list[float]] = [[] for _ in order]
    inference: list[list[float]] = [[] for _ in order]
    for round_index in range(rounds):
        for position, index in enumerate(order):
            training[position].append(timers[index].training_seconds_per_step())
            inference[position].append(timers[index].seconds_per_image())
        report(
            f"  timing round {round_index + 1}/{rounds}: " + ", ".join(f"{times[-1]:.3f} s/step" for times in training)
        )
    return [(statistics.median(train), statistics.median(infer)) for train, infer in zip(training, inference)]


def _quality(scores: dict[str, Any]) -> dict[str, Any]:
    keys = (*QUALITY_KEYS, *(f"background_{key}" for key in QUALITY_KEYS), "codes_used", "contact_fraction")
    return {key: scores[key] for key in keys if isinstance(scores.get(key), (int, float))}


def tokenizer_rows(
    baseline: Any,
    host: PluginHost,
    knobs: dict[str, list[Any]],
    *,
    seed: int,
    out: Path,
    rounds: int,
    timing_steps: int,
    argv: list[str],
    report: Callable[[str], None],
) -> tuple[list[dict], Path]:
    """One seed of part 1: the baseline's and every tokenizer knob value's row (scores, costs and
    costs relative to the baseline), then the baseline's drift row.  Also returns the baseline's
    run (where the generator trains)."""
    variants = [(None, None)] + [
        (name, value) for name, values in knobs.items() if KNOBS[name].part == "tokenizer" for value in values
    ]
    configs = [variant_config(baseline, host, seed, name, value) for name, value in variants]
    rows, runs = [], []
    for (name, value), config in zip(variants, configs):
        folder = (
            out
            / "runs"
            / f"seed{seed}"
            / ("baseline" if name is None else re.sub(r"[^A-Za-z0-9.]+", "_", f"{name}-{value}").strip("_"))
        )
        # The baseline's generator trains in the same run later (generator_rows), on this tokenizer.
        path, seconds = train_tokenizer_run(config, host, folder, argv)
        scores = json.loads((path / "eval.json").read_text())
        runs.append(path)
        rows.append(
            {
                "part": "tokenizer",
                "knob": name or "baseline",
                "setting": baseline_text(config, host) if name is None else KNOBS[name].show(value),
                "seed": seed,
                "stage_seconds": round(seconds, 2),
                "run": str(path),
                **_quality(scores),
            }
        )
        report(
            f"seed {seed}: tokenizer {rows[-1]['knob']} {rows[-1]['setting']}: SSIM {scores.get('ssim')}, "
            f"contact SSIM {scores.get('contact_ssim')} (background {scores.get('background_contact_ssim')}), "
            f"{seconds:.0f} s"
        )
    report(f"seed {seed}: timing {len(configs)} tokenizers, {rounds} interleaved rounds of {timing_steps} steps")
    timers = [TokenizerTimer(config, path, host, timing_steps) for config, path in zip(configs, runs)]
    costs = time_tokenizers(timers, rounds, report)
    rows.append({"part": "tokenizer", "knob": "baseline", "setting": DRIFT, "seed": seed})
    base_step, base_image = costs[0]
    for row, (per_step, per_image) in zip(rows, costs):
        row |= {
            "train_s_per_step": round(per_step, 6),
            "train_cost": round(per_step / base_step, 4),
            "seconds_per_image": round(per_image, 6),
            "img_per_s": round(1 / per_image, 4),
            "inference_cost": round(per_image / base_image, 4),
        }
    return rows, runs[0]


def generator_rows(
    run: Path,
    config: Any,
    host: PluginHost,
    knobs: dict[str, list[Any]],
    *,
    seed: int,
    n: int,
    rounds: int,
    batch_size: int,
    distribution: bool,
    report: Callable[[str], None],
) -> list[dict[str, Any]]:
    """One seed of part 2: train the generator in the baseline's ``run`` (on its tokenizer's codes),
    then time and score every sampling setting with ``vqtouch tradeoff generator``'s functions, the
    configured setting first and again last (drift)."""
    from vqtouch.plugins.generator import check_settings, load_tradeoff_bench, measure, sweep_settings

    with RunDir.open(run, for_writing=True) as run_dir:
        outcome = run_stage("generator", Assembly(config, host), run_dir)
    if outcome.status != "ran":
        raise stage_failure(outcome)
    report(f"seed {seed}: generator trained in {outcome.seconds:.0f} s")
    bench = load_tradeoff_bench(run, host, n=n, batch_size=batch_size, distribution=False)
    base = generator_base(config)
    lists = {key: [base[key]] for key in base}
    for name, values in knobs.items():
        if KNOBS[name].part == "generator":
            lists[KNOBS[name].setting_key] += values
    check_settings(bench, lists["steps"], lists["sampler"], lists["guidance"], lists["precision"])
    if distribution:
        bench.fit_distribution()
    settings = sweep_settings(
        steps=lists["steps"],
        samplers=lists["sampler"],
        guidance=lists["guidance"],
        precisions=lists["precision"],
        base=base,
    )
    measured = measure(bench, [*settings, base], rounds, log=_ReportLog(report))
    background = bench.score(bench.background, "background_") if bench.background is not None else {}
    knob_of = {KNOBS[name].setting_key: name for name in KNOBS if KNOBS[name].part == "generator"}
    rows = []
    for index, (setting, result) in enumerate(zip([*settings, base], measured)):
        changed = [key for key in base if setting[key] != base[key]]
        if changed:
            knob = knob_of[changed[0]]
            text = KNOBS[knob].show(setting[changed[0]])
        else:
            knob, text = "baseline", DRIFT if index == len(settings) else result["label"]
        # The drift row repeats the baseline's images: a timing, not a contender.
        quality = (
            {}
            if text == DRIFT
            else {
                **_quality(result | background),
                **{key: result[key] for key in ("classifier_accuracy", "fd_effnetlite0") if key in result},
            }
        )
        rows.append(
            {
                "part": "generator",
                "knob": knob,
                "setting": text,
                "seed": seed,
                "sampling": setting,
                **quality,
                "seconds_per_image": result["seconds_per_image"],
                "img_per_s": result["img_per_s"],
                "inference_cost": result["cost"],
                "reproducible": result["reproducible"],
                "run": str(run),
            }
        )
    return rows


class _ReportLog:
    """A file-like ``log`` for :func:`measure` that hands each line to ``report``."""

    def __init__(self, report: Callable[[str], None]) -> None:
        self.report = report

    def write(self, text: str) -> None:
        if text.strip():
            self.report("  " + text.rstrip("\n"))

    def flush(self) -> None:
        pass


# -- the experiment -------------------------------------------------------------------------------


def evaluate_tradeoff(
    config: Any,
    host: PluginHost,
    out: Path,
    *,
    seeds: list[int],
    knobs: dict[str, list[Any]],
    full: bool,
    tokenizer_steps: int,
    generator_steps: int,
    rounds: int,
    timing_steps: int,
    n: int,
    batch_size: int,
    distribution: bool,
    argv: list[str],
    report: Callable[[str], None] = print,
    overwrite: bool = False,
) -> dict[str, Any]:
    """Both parts for every seed (see the module docstring) around ``config`` (already
    :func:`~vqtouch.plugins.experiments.pipeline_tradeoff_configs.scaled_config`; ``full`` says whether
    it was scaled down); writes ``tradeoff.json``, ``tradeoff.md`` and ``tradeoff.png`` into ``out``
    (one that holds them only with ``overwrite``) and returns the result."""
    settings = _Settings(full, tokenizer_steps, generator_steps, rounds, timing_steps, n, batch_size, distribution)
    record = ExperimentRecord("tradeoff", out, seeds, overwrite=overwrite)
    generator = any(KNOBS[name].part == "generator" for name in knobs)
    baseline = baseline_config(
        config, host, tokenizer_steps=tokenizer_steps, generator_steps=generator_steps, generator=generator
    )
    _check_values(baseline, host, knobs, seeds[0])
    rows: list[dict[str, Any]] = []
    for seed in seeds:
        rows += _seed_rows(baseline, host, knobs, seed, out, settings, generator, argv, report)
    summary, key = summarize(rows)
    result = _result(baseline, host, knobs, seeds, settings, generator, rows, summary, key)
    record.write(result, render_markdown(result))
    plot_tradeoff(
        summary,
        key,
        record.path("tradeoff.png"),
        f"{baseline.scene}: {len(seeds)} seeds, {tokenizer_steps} tokenizer steps, {torch.get_num_threads()} threads",
    )
    return result


@dataclasses.dataclass(frozen=True)
class _Settings:
    """How much :func:`evaluate_tradeoff` trains, times and samples (``tradeoff.json``'s ``settings``)."""

    full: bool
    tokenizer_steps: int
    generator_steps: int
    rounds: int
    timing_steps: int
    n: int
    batch_size: int
    distribution: bool


def _check_values(baseline: Any, host: PluginHost, knobs: dict[str, list[Any]], seed: int) -> None:
    """One-line errors for any knob value that makes no valid variant or sampling setting."""
    # Every value is checked before anything trains: a bad one would otherwise fail an hour in.
    for name, values in knobs.items():
        if KNOBS[name].part == "tokenizer":
            for value in values:
                variant_config(baseline, host, seed, name, value)
    check_sampling_values(baseline, host, knobs)


def _seed_rows(
    baseline: Any,
    host: PluginHost,
    knobs: dict[str, list[Any]],
    seed: int,
    out: Path,
    settings: _Settings,
    generator: bool,
    argv: list[str],
    report: Callable[[str], None],
) -> list[dict[str, Any]]:
    """One seed of both parts: the tokenizer rows, then (with ``generator``) the generator rows."""
    rows, baseline_run = tokenizer_rows(
        baseline,
        host,
        knobs,
        seed=seed,
        out=out,
        rounds=settings.rounds,
        timing_steps=settings.timing_steps,
        argv=argv,
        report=report,
    )
    if generator:
        rows += generator_rows(
            baseline_run,
            variant_config(baseline, host, seed),
            host,
            knobs,
            seed=seed,
            n=settings.n,
            rounds=settings.rounds,
            batch_size=settings.batch_size,
            distribution=settings.distribution,
            report=report,
        )
    return rows


def _result(
    baseline: Any,
    host: PluginHost,
    knobs: dict[str, list[Any]],
    seeds: list[int],
    settings: _Settings,
    generator: bool,
    rows: list[dict[str, Any]],
    summary: list[dict[str, Any]],
    key: str,
) -> dict[str, Any]:
    """What ``tradeoff.json`` holds (beside the record's seeds and provenance)."""
    base = generator_base(baseline) if generator else None
    return {
        "seeds": seeds,
        "scene": baseline.scene,
        "baseline": baseline_text(baseline, host),
        "generator_baseline": (
            f"{base['sampler']}, {base['steps']} steps, guidance {base['guidance']:g}, {base['precision']}"
        )
        if base
        else None,
        "knobs": {name: [KNOBS[name].show(value) for value in values] for name, values in knobs.items()},
        "settings": dataclasses.asdict(settings),
        "front_quality": key,
        "config": baseline.to_dict(),
        "rows": rows,
        "summary": summary,
    }


def _command(args: argparse.Namespace) -> int:
    host = args.host
    if not (args.scene_positional or args.scene):
        args.scene = DEFAULT_SCENE
    if args.threads:
        torch.set_num_threads(args.threads)
    config = scaled_config(config_from_args(args, host), host, args.full)
    preset = QUICK if args.quick else STANDARD
    chosen = {key: getattr(args, key) if getattr(args, key) is not None else value for key, value in preset.items()}
    specs = args.knobs
    if specs is None and args.quick:
        specs = [name for name in QUICK_KNOBS if KNOBS[name].part == "tokenizer" or "generator" in config.stages]
    knobs = parse_knobs(specs, config, host)
    out = Path(args.out)
    evaluate_tradeoff(
        config,
        host,
        out,
        seeds=args.seeds,
        knobs=knobs,
        full=args.full,
        batch_size=args.batch_size,
        distribution=args.distribution,
        argv=args.argv,
        report=lambda line: print(line, file=sys.stderr, flush=True),
        overwrite=args.overwrite,
        **chosen,
    )
    print((out / "tradeoff.md").read_text())
    print(f"-> {out} (tradeoff.json, tradeoff.md, tradeoff.png; the trained runs in {out / 'runs'})")
    return 0

"""``vqtouch tradeoff generator``: the sampling cost and the quality of a trained generator, knob by
knob, measured in one process.

::

    vqtouch tradeoff generator --run runs/l2t --out runs/l2t/tradeoff --n 60 --rounds 2

The pipeline is loaded once and every setting (sampler x steps x guidance x precision; one knob
at a time around a base setting, or ``--grid``) generates the same held-out conditions with the
same seeds (those of :func:`.scoring.score_generation`).  Only generation is timed (condition
encoding, sampling and decoding, after a warm-up), ``--rounds`` times, interleaved (round 1 of
every setting, then round 2, ...), so machine drift hits every setting alike; the median is
reported and cost ratios are against the first row.  Quality is scored once per setting, outside
the timed part, by the functions the stage uses (:func:`.scoring.score_images`): SSIM, PSNR and
contact PSNR against the ground truth of each condition, ``fd_effnetlite0`` against the real
held-out images and the accuracy of a classifier trained on real images
(:class:`vqtouch.plugins.evaluation.distribution.DistributionScorer`, fitted once).

Writes ``tradeoff.json`` (every measurement), ``tradeoff.md`` (the table) and ``pareto.png``
(time per image against each quality, the Pareto front drawn).  ``bench/bench_generator.py``
measures the same settings' peak memory, each in a fresh interpreter, with these functions.
"""

from __future__ import annotations

import argparse
import hashlib
import itertools
import json
import math
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from vqtouch.plugins.runtime.outputs import output_folder
from vqtouch.core import Assembly, ConfigError, PluginHost
from vqtouch.plugins.runtime.run_dir import MissingCheckpointError
from vqtouch.plugins.evaluation.contact import dataset_background

from .best_of import check_best_of, check_best_of_rank
from .rankers_plugin import DEFAULT_RANKER
from .scoring import (
    PRECISIONS,
    HeldOutConditions,
    baseline_pool,
    distribution_scorer,
    generate_held_out,
    held_out_conditions,
    score_images,
)

#: The knobs of a setting, in the order of the table's columns.
KNOBS = ("sampler", "steps", "guidance", "precision")

#: Quality columns: (key, label, higher is better).  ``contact_psnr`` falls back to ``psnr``
#: without a background (no no-contact image, no contact region).
QUALITIES = (
    ("contact_psnr", "contact PSNR (dB)", True),
    ("contact_centroid_error_px", "contact centroid error (px)", False),
    ("fd_effnetlite0", "fd_effnetlite0", False),
    ("classifier_accuracy", "classifier accuracy", True),
)


def sweep_settings(
    *,
    steps: list[int],
    samplers: list[str],
    guidance: list[float],
    precisions: list[str],
    grid: bool = False,
    batches: list[int] | None = None,
    base: dict[str, Any] | None = None,
    best_of: list[int] | None = None,
) -> list[dict[str, Any]]:
    """The settings to measure.  ``grid``: every combination.  Otherwise one knob at a time around
    the base (the first sampler, guidance, precision and batch, and the middle of ``steps``; or
    ``base``, e.g. a run's configured setting, each list then starting with its value): first every
    ``steps`` value, then the other samplers, guidance values, precisions and batches.
    Duplicates are dropped, the order kept; the first row is the cost reference.  ``batches`` and
    ``best_of`` (None: not a knob) add a ``batch`` and a ``best_of`` entry to every setting."""
    lists = {"sampler": samplers, "steps": steps, "guidance": guidance, "precision": precisions}
    if batches is not None:
        lists["batch"] = batches
    if best_of is not None:
        lists["best_of"] = best_of
    if grid:
        settings = [dict(zip(lists, combo)) for combo in itertools.product(*lists.values())]
    else:
        if base is None:
            base = {key: values[0] for key, values in lists.items()} | {"steps": steps[len(steps) // 2]}
        settings = [{**base, "steps": value} for value in steps]
        for key in ("sampler", "guidance", "precision", "batch", "best_of"):
            settings += [{**base, key: value} for value in lists.get(key, [])[1:]]
    unique = dict.fromkeys(tuple(setting.items()) for setting in settings)
    return [dict(items) for items in unique]


def setting_label(setting: dict[str, Any]) -> str:
    """A short name of a setting for the plot: ``posterior 25``, ``purity 10 g3 bf16``."""
    label = f"{setting['sampler']} {setting['steps']}"
    if setting["guidance"] != 1:
        label += f" g{setting['guidance']:g}"
    if setting["precision"] != "fp32":
        label += f" {setting['precision']}"
    if "batch" in setting:
        label += f" b{setting['batch']}"
    if setting.get("best_of", 1) != 1:
        label += f" best{setting['best_of']}"
    return label


def pareto_front(costs: list[float], qualities: list[float | None], higher_is_better: bool = True) -> list[int]:
    """Indices of the points on the Pareto front of (cost, quality), cheapest first: a point is on
    it when no other point is at least as cheap and at least as good and strictly better in one of
    the two (of identical points only the first).  Points without a quality (None, NaN) are on no
    front."""
    sign = 1.0 if higher_is_better else -1.0
    usable = [
        i
        for i, quality in enumerate(qualities)
        if quality is not None and not math.isnan(quality) and not math.isnan(costs[i])
    ]
    # Cheapest first, and at equal cost the best first: a point is on the front when it beats the
    # best quality of every point before it.
    order = sorted(usable, key=lambda i: (costs[i], -sign * qualities[i], i))
    front, best = [], -math.inf
    for index in order:
        if sign * qualities[index] > best:
            front.append(index)
            best = sign * qualities[index]
    return front


@dataclass
class TradeoffBench:
    """A loaded generator run and the held-out conditions every setting generates and is scored on."""

    pipe: Any
    run: Path
    conditions: HeldOutConditions
    metrics: list[tuple[str, Any]]
    background: torch.Tensor | None
    seed: int
    batch_size: int
    train: Any
    feature_size: int = 224
    scorer: Any = None
    #: How :attr:`background` was made (:func:`~vqtouch.plugins.evaluation.contact.dataset_background`).
    background_source: str = ""
    #: The registered best-of ranker that ranks best of K's candidates (:mod:`.best_of`).
    best_of_rank: str = DEFAULT_RANKER
    #: Which of the generator's conditioners generates (its index; :meth:`choose_conditioner`).
    conditioner: int = 0

    def choose_conditioner(self, which: int | str) -> None:
        """Generate with the run's conditioner ``which`` (index or name), or a one-line ConfigError
        naming them (the pipeline's lookup, as ``vqtouch generate --conditioner``)."""
        self.conditioner = self.pipe._conditioner_index(which, self.pipe.conditioner_names())

    def fit_distribution(self, feature_size: int | None = None, classifier_on: str = "real") -> None:
        """Fit the distribution scorer (:func:`.scoring.distribution_scorer`): the real held-out
        images' features and the classifier on the training split's real images (``classifier_on``
        ``"reconstructions"``: on the tokenizer's reconstructions of them, which judges decoded images
        fairly), EfficientNet-Lite0 features at ``feature_size`` px (None: :attr:`feature_size`, the
        run's ``fd_effnetlite0`` metric's, else 224).  Once; every setting's images are then scored
        with it."""
        from vqtouch.plugins.evaluation.fd_metric import FdEffNetLite0

        if classifier_on not in ("real", "reconstructions"):
            raise ValueError(f"classifier_on {classifier_on!r}: expected 'real' or 'reconstructions'")
        if feature_size is not None:
            self.feature_size = feature_size
        metric = FdEffNetLite0(image_size=self.feature_size)
        self.scorer = distribution_scorer(
            self.conditions,
            baseline_pool(self.train),
            [("fd_effnetlite0", metric)],
            self.seed,
            tokenizer=self.pipe.tokenizer if classifier_on == "reconstructions" else None,
        )

    def sampler(self, name: str) -> Any:
        """The sampler plugin ``name`` (the registry's error lists the samplers there are)."""
        return self.pipe.sampler if name == self.pipe.sampler_name else self.pipe.host.build("sampler", name)

    def generate(self, setting: dict[str, Any], conditions: HeldOutConditions | None = None) -> torch.Tensor:
        """The images of the held-out conditions (or ``conditions``) under ``setting``."""
        pipe = self.pipe
        return generate_held_out(
            pipe.generator,
            pipe.conditioners[self.conditioner],
            pipe.tokenizer,
            self.sampler(setting["sampler"]),
            conditions or self.conditions,
            steps=setting["steps"],
            guidance=setting["guidance"],
            truncation=pipe.settings["truncation"],
            seed=self.seed,
            device=pipe.device,
            batch_size=setting.get("batch", self.batch_size),
            precision=setting["precision"],
            best_of=setting.get("best_of", 1),
            rank=pipe.best_of_ranking(self.best_of_rank) if setting.get("best_of", 1) > 1 else None,
        )

    def timed(self, setting: dict[str, Any]) -> tuple[float, torch.Tensor]:
        """Seconds to generate (encode, sample, decode) the held-out conditions, and the images."""
        synchronize(self.pipe.device)
        tic = time.perf_counter()
        images = self.generate(setting)
        synchronize(self.pipe.device)
        return time.perf_counter() - tic, images

    def warm_up(self, settings: list[dict[str, Any]]) -> None:
        """One step on one batch for each sampler x precision x (guided or not) among ``settings``:
        lazy initialisation and first-call costs stay out of the timings."""
        rows = min(self.batch_size, len(self.conditions.indices))
        first = HeldOutConditions(
            self.conditions.samples[:rows], self.conditions.indices[:rows], self.conditions.truth[:rows], None
        )
        if any(setting.get("best_of", 1) > 1 for setting in settings):
            self.pipe.best_of_ranking(self.best_of_rank)  # prepared once, untimed (the judge is fitted)
        seen = set()
        for setting in settings:
            key = (setting["sampler"], setting["precision"], setting["guidance"] != 1, setting.get("batch"))
            if key not in seen:
                seen.add(key)
                self.generate({**setting, "steps": 1}, first)

    def score(self, images: torch.Tensor, prefix: str = "") -> dict[str, Any]:
        """Quality of one image set of the held-out conditions (the stage's scores)."""
        return score_images({prefix: images}, self.conditions.truth, self.metrics, self.background, self.scorer)


def synchronize(device: torch.device) -> None:
    """Wait for the device's queued work (timings on a GPU)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def load_tradeoff_bench(
    run: str | Path,
    host: PluginHost,
    *,
    n: int,
    step: int | str | None = None,
    seed: int | None = None,
    batch_size: int = 16,
    distribution: bool = True,
    feature_size: int | None = None,
) -> TradeoffBench:
    """The run's pipeline, its first ``n`` held-out conditions (the split of
    ``vqtouch evaluate generation``), SSIM and PSNR, the no-contact image (of the training split:
    :func:`~vqtouch.plugins.evaluation.contact.dataset_background`) and, with
    ``distribution``, the distribution scorer (classifier fitted on the training split's real images,
    EfficientNet-Lite0 features at ``feature_size`` px; None: the run's ``fd_effnetlite0`` metric's,
    else 224)."""
    from vqtouch.plugins.utils.splits import experiment_split

    from .pipeline import load_pipeline

    try:
        pipe = load_pipeline(run, host=host, step=step)
    except MissingCheckpointError as exc:
        raise ConfigError(f"no trained generator in {run} ({exc}); train one with `vqtouch train generator`") from None
    config = pipe.config
    where = pipe.run.path if pipe.run is not None else Path(str(run))  # a bundle: its name, pretrained:NAME
    assembly = Assembly(config, host)
    dataset = assembly.component("data.dataset")
    train, held_out = experiment_split(dataset, config.data, config.seed)
    seed = config.seed if seed is None else seed
    conditions = held_out_conditions(held_out, dataset, n, pipe.device)
    metrics = [(name, host.build("metric", name)) for name in ("ssim", "psnr")]
    background_3HW, background_source = dataset_background(train, tuple(conditions.truth.shape[-2:]))
    background = None if background_3HW is None else background_3HW.to(conditions.truth).expand_as(conditions.truth)
    run_size = next((item.image_size for item in config.metrics if item.name == "fd_effnetlite0"), 224)
    bench = TradeoffBench(
        pipe,
        where,
        conditions,
        metrics,
        background,
        seed,
        batch_size,
        train,
        feature_size if feature_size is not None else run_size,
        background_source=background_source,
    )
    if distribution:
        bench.fit_distribution()
    return bench


def check_settings(
    bench: TradeoffBench,
    steps: list[int],
    samplers: list[str],
    guidance: list[float],
    precisions: list[str],
    best_of: list[int] | None = None,
) -> None:
    """One-line errors for values no setting can take, before anything is timed."""
    if not (steps and samplers and guidance and precisions):
        raise ConfigError("give at least one value of each of --steps, --samplers, --guidance and --precisions")
    for value in steps:
        bench.pipe.check_steps(value)
    for value in guidance:
        if not value >= 0 or math.isinf(value):
            raise ConfigError(f"--guidance {value:g}: the guidance scale must be a finite number >= 0 (1: unguided)")
    for name in precisions:
        if name not in PRECISIONS:
            raise ConfigError(f"--precisions {name}: expected {' or '.join(PRECISIONS)}")
    for name in samplers:
        bench.sampler(name)  # an unknown name raises the registry's error, which lists the samplers
    for value in best_of or []:
        check_best_of(
            value,
            bench.pipe.conditioners[bench.conditioner],
            bench.pipe.conditioner_names()[bench.conditioner],
            bench.pipe.best_of_ranker(bench.best_of_rank),
        )


def measure(bench: TradeoffBench, settings: list[dict[str, Any]], rounds: int, log: Any = None) -> list[dict[str, Any]]:
    """Time every setting ``rounds`` times, interleaved, and score each once; the rows of the table.
    Progress goes to ``log`` (default: stderr), one line per setting and round."""
    log = log or sys.stderr
    bench.warm_up(settings)
    seconds: list[list[float]] = [[] for _ in settings]
    scores: list[dict[str, Any]] = [{} for _ in settings]
    digests: list[set[str]] = [set() for _ in settings]
    count = len(bench.conditions.indices)
    for round_index in range(rounds):
        for index, setting in enumerate(settings):
            elapsed, images = bench.timed(setting)
            seconds[index].append(elapsed)
            digests[index].add(hashlib.sha256(images.cpu().numpy().tobytes()).hexdigest())
            if round_index == 0:
                scores[index] = bench.score(images)
            shown = ", ".join(
                f"{key} {scores[index][key]:g}"
                for key in ("ssim", *(q[0] for q in QUALITIES))
                if isinstance(scores[index].get(key), float)
            )
            print(
                f"[round {round_index + 1}/{rounds}, setting {index + 1}/{len(settings)}] {setting_label(setting)}: "
                f"{count / elapsed:.2f} img/s; {shown}",
                file=log,
                flush=True,
            )
    reference = statistics.median(seconds[0]) / count
    rows = []
    for setting, times, score, digest in zip(settings, seconds, scores, digests):
        per_image = statistics.median(times) / count
        rows.append(
            {
                **setting,
                "label": setting_label(setting),
                "img_per_s": round(1 / per_image, 4),
                "seconds_per_image": round(per_image, 6),
                "cost": round(per_image / reference, 4),
                "seconds": [round(t, 4) for t in times],
                "reproducible": len(digest) == 1,
                **score,
                "pareto": [],
            }
        )
    for key, _, higher in QUALITIES:
        key = quality_key(rows, key)
        for index in pareto_front([row["seconds_per_image"] for row in rows], [row.get(key) for row in rows], higher):
            rows[index]["pareto"].append(key)
    return rows


def quality_key(rows: list[dict[str, Any]], key: str) -> str:
    """``key``, or ``psnr`` for a contact PSNR that no row has (no background)."""
    if key == "contact_psnr" and not any(key in row for row in rows):
        return "psnr"
    return key


def _cell(value: Any, digits: int) -> str:
    return "–" if not isinstance(value, (int, float)) else f"{value:.{digits}f}"


def markdown_table(rows: list[dict[str, Any]], header: str, reference: dict[str, Any]) -> str:
    """``tradeoff.md``: the header line, the table (one row per setting) and the reference scores."""
    # The best-of column only when it is a knob of the sweep.
    best_of = any("best_of" in row for row in rows)
    lines = [
        header,
        "",
        "| sampler | steps | guidance | precision | "
        + ("best of | " if best_of else "")
        + "img/s | ms/img | cost | SSIM | PSNR dB | contact PSNR dB | centroid px | fd_effnetlite0 | classifier acc | "
        "Pareto front |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|" + ("---|" if best_of else ""),
    ]
    for row in rows:
        lines.append(
            f"| {row['sampler']} | {row['steps']} | {row['guidance']:g} | {row['precision']} | "
            + (f"{row.get('best_of', 1)} | " if best_of else "")
            + f"{row['img_per_s']:.2f} | {row['seconds_per_image'] * 1000:.1f} | {row['cost']:.2f}x | "
            f"{_cell(row.get('ssim'), 4)} | {_cell(row.get('psnr'), 2)} | "
            f"{_cell(row.get('contact_psnr'), 2)} | {_cell(row.get('contact_centroid_error_px'), 2)} | "
            f"{_cell(row.get('fd_effnetlite0'), 2)} | {_cell(row.get('classifier_accuracy'), 3)} | "
            f"{', '.join(row.get('pareto', [])) or '–'} |"
        )
    if reference:
        lines += [
            "",
            "References on the same conditions: "
            + "; ".join(f"{key} {value}" for key, value in reference.items())
            + ".",
        ]
    return "\n".join(lines) + "\n"


def plot_pareto(rows: list[dict[str, Any]], path: Path, title: str, reference: dict[str, Any]) -> None:
    """``pareto.png``: one panel per quality column the rows have (contact PSNR, fd_effnetlite0,
    classifier accuracy), time per image on a log x axis, every setting a labelled point, the
    Pareto front a line, and the reference scores (real images, the tokenizer's reconstructions, the
    no-contact image) as grey lines."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import NullFormatter

    panels = [(quality_key(rows, key), label, higher) for key, label, higher in QUALITIES]
    panels = [
        (key, "PSNR (dB)" if key == "psnr" else label, higher)
        for key, label, higher in panels
        if any(isinstance(row.get(key), (int, float)) for row in rows)
    ]
    figure = Figure(figsize=(5.5 * len(panels), 4.5), layout="constrained")
    FigureCanvasAgg(figure)
    costs = [row["seconds_per_image"] for row in rows]
    for number, (key, label, higher) in enumerate(panels):
        axes = figure.add_subplot(1, len(panels), number + 1)
        points = [
            (cost, row[key], row["label"]) for cost, row in zip(costs, rows) if isinstance(row.get(key), (int, float))
        ]
        axes.scatter([p[0] for p in points], [p[1] for p in points], s=18, color="tab:blue", zorder=3)
        for x, y, text in points:
            axes.annotate(text, (x, y), textcoords="offset points", xytext=(4, 3), fontsize=7)
        front = pareto_front(costs, [row.get(key) for row in rows], higher)
        axes.plot(
            [costs[i] for i in front],
            [rows[i][key] for i in front],
            color="tab:red",
            marker="o",
            linewidth=1.5,
            label="Pareto front",
            zorder=2,
        )
        for prefix, style, text in (
            ("real_", "--", "real held-out images"),
            ("ceiling_", "-.", "tokenizer's reconstructions"),
            ("background_", ":", "no-contact image"),
        ):
            if isinstance(reference.get(prefix + key), (int, float)):
                axes.axhline(reference[prefix + key], linestyle=style, color="grey", linewidth=1, label=text)
        axes.set_xscale("log")
        axes.xaxis.set_minor_formatter(NullFormatter())  # labelled minor ticks overlap on a short log axis
        axes.set_xlabel("seconds per image (log scale)")
        axes.set_ylabel(f"{label} ({'higher' if higher else 'lower'} is better)")
        axes.grid(True, which="both", alpha=0.3)
        axes.legend(fontsize=7)
    figure.suptitle(title, fontsize=9)
    figure.savefig(path, dpi=120)


def tradeoff_command(args: argparse.Namespace) -> int:
    """``vqtouch tradeoff generator``."""
    if args.threads:
        torch.set_num_threads(args.threads)
    bench = _checked_bench(args)
    settings = sweep_settings(
        steps=args.steps,
        samplers=args.samplers,
        guidance=args.guidance,
        precisions=args.precisions,
        grid=args.grid,
        best_of=args.best_of,
    )
    out = output_folder(args.out)
    count = len(bench.conditions.indices)
    print(
        f"{len(settings)} settings x {args.rounds} rounds on {count} held-out conditions of {bench.run}",
        file=sys.stderr,
        flush=True,
    )
    rows = measure(bench, settings, args.rounds)
    reference = _reference_scores(bench, args.classifier_on)
    result = _tradeoff_record(bench, args, rows, reference)
    (out / "tradeoff.json").write_text(json.dumps(result, indent=2) + "\n")
    table = markdown_table(rows, _table_header(bench, args, rows), reference)
    (out / "tradeoff.md").write_text(table)
    plot_pareto(
        rows,
        out / "pareto.png",
        f"{bench.run.name}: n = {count}, {result['device']}, {torch.get_num_threads()} threads",
        reference,
    )
    print(table)
    print(f"-> {out} (tradeoff.json, tradeoff.md, pareto.png)")
    return 0


def _checked_bench(args: argparse.Namespace) -> TradeoffBench:
    """The command's bench: the run loaded, its conditioner and ranker chosen, every knob's values
    checked before anything is timed, the distribution scorer fitted when asked."""
    bench = load_tradeoff_bench(
        args.run,
        args.host,
        n=args.n,
        step=args.step,
        seed=args.seed,
        batch_size=args.batch_size,
        distribution=False,
        feature_size=args.feature_size,
    )
    bench.choose_conditioner(args.conditioner)
    bench.best_of_rank = check_best_of_rank(args.best_of_rank, args.host)
    check_settings(bench, args.steps, args.samplers, args.guidance, args.precisions, args.best_of)
    if args.distribution:
        bench.fit_distribution(classifier_on=args.classifier_on)
    return bench


#: The reference scores ``tradeoff.json`` keeps of the tokenizer's reconstructions and of the no-contact image.
_CEILING_KEYS = ("contact_psnr", "contact_centroid_error_px", "fd_effnetlite0", "classifier_accuracy")
_BACKGROUND_KEYS = ("ssim", "psnr", *_CEILING_KEYS)


def _reference_scores(bench: TradeoffBench, classifier_on: str) -> dict[str, Any]:
    """The scores every setting is compared with, on the same conditions: the real images' classifier
    accuracy, the tokenizer's own reconstructions of the truth (``ceiling_*``: what no generator over
    its codes can beat) and the no-contact image (``background_*``); those that could be scored."""
    reference: dict[str, Any] = {}
    if bench.scorer is not None:
        real = bench.scorer.real_scores()
        reference |= {
            # Fitted on reconstructions, the classifier's accuracy on sharp real images is no reference.
            "real_classifier_accuracy": real.get("real_classifier_accuracy") if classifier_on == "real" else None,
            "classifier_train_images": real.get("classifier_train_images"),
            "classifier_skipped": real.get("classifier_skipped"),
        }
    tokenizer = bench.pipe.tokenizer
    with torch.no_grad():
        reconstructions = tokenizer.decode_codes(tokenizer.encode_codes(bench.conditions.truth)).float()
    ceiling = bench.score(reconstructions, "ceiling_")
    reference |= {f"ceiling_{key}": ceiling.get(f"ceiling_{key}") for key in _CEILING_KEYS}
    if bench.background is not None:
        background = bench.score(bench.background, "background_")
        reference |= {f"background_{key}": background.get(f"background_{key}") for key in _BACKGROUND_KEYS}
    return {key: value for key, value in reference.items() if value is not None}


def _table_header(bench: TradeoffBench, args: argparse.Namespace, rows: list[dict[str, Any]]) -> str:
    """``tradeoff.md``'s first line: what was measured, where and how."""
    return (
        f"Generator trade-off: run `{bench.run}` ({bench.pipe.checkpoint.name}); conditioner "
        f"{bench.pipe.conditioner_names()[bench.conditioner]}; n = {len(bench.conditions.indices)} held-out "
        f"conditions; threads {torch.get_num_threads()}; rounds {args.rounds} (interleaved, median); device "
        f"{bench.pipe.device}; batch {args.batch_size}; seed {bench.seed}; "
        f"truncation {bench.pipe.settings['truncation']:g}; "
        f"features {bench.feature_size} px"
        + (f"; classifier on the {args.classifier_on} of the training images" if args.distribution else "")
        + (f"; best of K ranked by the {bench.best_of_rank}" if any(r.get("best_of", 1) > 1 for r in rows) else "")
        + "; cost = time per image / the first row's."
    )


def _tradeoff_record(
    bench: TradeoffBench, args: argparse.Namespace, rows: list[dict[str, Any]], reference: dict[str, Any]
) -> dict[str, Any]:
    """``tradeoff.json``: the run, how it was measured, the reference scores and every setting's row."""
    return {
        "run": str(bench.run),
        "checkpoint": str(bench.pipe.checkpoint),
        "conditioner": bench.pipe.conditioner_names()[bench.conditioner],
        "n": len(bench.conditions.indices),
        "rounds": args.rounds,
        "best_of_rank": bench.best_of_rank,
        "threads": torch.get_num_threads(),
        "device": str(bench.pipe.device),
        "batch_size": args.batch_size,
        "seed": bench.seed,
        "truncation": bench.pipe.settings["truncation"],
        "feature_size": bench.feature_size,
        "distribution": bool(args.distribution),
        **({"classifier_trained_on": f"the {args.classifier_on} of the training images"} if args.distribution else {}),
        "grid": bool(args.grid),
        "background": bench.background_source,
        "reference": reference,
        "settings": rows,
    }

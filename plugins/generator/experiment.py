"""``vqtouch evaluate generation --out DIR``: the paper's Table 2, generation per conditioner, over seeds.

::

    vqtouch evaluate generation --out runs/exp/generation --scene tour [--tokenizer RUN] [--seeds 0 1 2] \\
        [--n 32] [--set generator.train.steps=1000 ...]

One tokenizer (``--tokenizer RUN``, or the scene's tokenizer trained once into ``DIR/tokenizer``)
and, per seed, one generator trained with the scene's generator section (every conditioner it
lists, one condition per training step) into ``DIR/seed<S>``.  Each conditioner then generates the
same ``--n`` held-out conditions, scored by the generator stage's own scorer against their ground
truth: every metric of the scene (SSIM, PSNR, MS-SSIM, LPIPS and the CLIP score when their weights
are there, reported as skipped otherwise), ``fd_effnetlite0`` and a real-image classifier's
accuracy (always), next to the baselines under the same protocol: the data's no-contact image
(draws nothing), retrieval of the nearest training image by the conditioner's tokens, the label's
mean training image, and the tokenizer's reconstruction of the ground truth (the ceiling).

The seed sets the generator's initialisation, data order and sampling draws; the data, the split
and the tokenizer are the same for every seed, so the spread is that of training a generator.
``generation.json`` holds every row, ``generation.md`` the table (mean ± std) and the verdicts,
which compare contact-region scores only, ``generation.png`` the contact PSNR and
``fd_effnetlite0`` per conditioner against the baselines.

It runs on the embedded procedural data or on any dataset the scene names, e.g. a folder in a
supported reader's layout: ``--set 'data.dataset={"name": "touch_and_go", "root": "..."}'``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from vqtouch.core import Assembly, ConfigError, PluginHost
from vqtouch.plugins.runtime.execution import run_stage
from vqtouch.plugins.runtime.run_dir import RunDir
from vqtouch.plugins.cli.app import stage_failure
from vqtouch.core.config import validate_experiment
from vqtouch.plugins.evaluation.records import (
    ExperimentRecord,
    gap_verdict,
    markdown_table,
    mean_spread,
)
from vqtouch.plugins.evaluation.directions import direction_arrow, lower_is_better

#: Numbers of a score dict that describe the sampling, not the quality.
FACTS = ("samples", "steps", "guidance", "truncation", "contact_fraction")
#: The comparisons the generator stage scores beside every generated image, by key prefix.
BASELINES = {
    "background_": "no-contact image",
    "retrieval_": "retrieval by condition tokens",
    "class_mean_": "label's mean training image",
    "real_": "real image (same condition)",
    "ceiling_": "ceiling: tokenizer reconstruction",
}
#: Columns of the table, in order, when present; any other score follows them.
PREFERRED = (
    "ssim",
    "psnr",
    "ms_ssim",
    "lpips",
    "contact_psnr",
    "contact_mae",
    "contact_centroid_error_px",
    "fd_effnetlite0",
    "classifier_accuracy",
)


def _is_score(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def score_keys(scores: dict[str, Any]) -> list[str]:
    """The generator's own scores in a conditioner's score dict: numbers that are neither facts of
    the sampling nor a baseline's (prefixed) copy."""
    return in_column_order(
        key
        for key, value in scores.items()
        if _is_score(value) and key not in FACTS and not key.startswith(tuple(BASELINES))
    )


def in_column_order(keys: Any) -> list[str]:
    """``keys`` without repeats, the :data:`PREFERRED` columns first in that order, then the others by name."""
    return sorted(
        dict.fromkeys(keys), key=lambda key: (PREFERRED.index(key) if key in PREFERRED else len(PREFERRED), key)
    )


def rows_of(generation: dict[str, Any], seed: int) -> list[dict[str, Any]]:
    """One row per (conditioner, method) of one seed's ``generation.json``: the generator's scores and
    each baseline's, with the prefix taken off so they share columns."""
    by_conditioner = generation.get("by_conditioner") or {f"0:{generation['conditioner']}": generation}
    rows = []
    for key, scores in by_conditioner.items():
        name = key.split(":", 1)[1]
        keys = score_keys(scores)
        rows.append(
            {"conditioner": name, "method": "generator", "seed": seed, **{score: scores[score] for score in keys}}
        )
        for prefix, method in BASELINES.items():
            values = {score: scores[prefix + score] for score in keys if _is_score(scores.get(prefix + score))}
            if values:
                rows.append({"conditioner": name, "method": method, "seed": seed, **values})
    return rows


def verdicts(summary: list[dict[str, Any]], key: str = "contact_psnr") -> list[str]:
    """Per conditioner, whether the generator beats the best non-ceiling baseline on the contact-region
    score ``key``, said only when the gap exceeds the two spreads together."""
    lines = []
    for conditioner in dict.fromkeys(row["conditioner"] for row in summary):
        rows = {row["method"]: row for row in summary if row["conditioner"] == conditioner and key in row}
        model = rows.get("generator")
        rivals = [row for method, row in rows.items() if method != "generator" and not method.startswith("ceiling")]
        if model is None or not rivals:
            continue
        sign = -1 if lower_is_better(key) else 1
        best = max(rivals, key=lambda row: sign * row[key])
        lines.append(f"- from `{conditioner}`: the generator {gap_verdict(model, best, key, best['method'])} on {key}.")
    return lines


def plot(summary: list[dict[str, Any]], path: Path, title: str) -> None:
    """Bars per conditioner and method with the seeds' spread: contact PSNR, and fd_effnetlite0 when scored."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    keys = [key for key in ("contact_psnr", "fd_effnetlite0") if any(key in row for row in summary)]
    conditioners = list(dict.fromkeys(row["conditioner"] for row in summary))
    methods = list(dict.fromkeys(row["method"] for row in summary))
    figure = Figure(figsize=(5 * max(1, len(keys)), 4), dpi=110)
    FigureCanvasAgg(figure)
    width = 0.8 / max(1, len(methods))
    for panel, key in enumerate(keys):
        axes = figure.add_subplot(1, len(keys), panel + 1)
        for index, method in enumerate(methods):
            cells = [
                next((row for row in summary if row["conditioner"] == c and row["method"] == method), {})
                for c in conditioners
            ]
            xs = [position + index * width for position in range(len(conditioners))]
            axes.bar(
                xs,
                [cell.get(key, float("nan")) for cell in cells],
                width,
                yerr=[cell.get(f"{key}_std", 0.0) for cell in cells],
                capsize=2,
                label=method,
            )
        axes.set_xticks([position + 0.4 - width / 2 for position in range(len(conditioners))], conditioners)
        axes.set_ylabel(key + (" (lower is better)" if lower_is_better(key) else " (higher is better)"))
        axes.grid(axis="y", alpha=0.3)
    if keys:
        figure.axes[0].legend(fontsize=7)
    figure.suptitle(title, fontsize=9)
    figure.tight_layout()
    figure.savefig(path)


def _tokenizer_run(config: Any, tokenizer: str | None, out: Path, host: PluginHost) -> str:
    """The tokenizer every seed's generator learns: ``tokenizer``, or the scene's trained once in ``out``."""
    if tokenizer:
        return tokenizer
    folder = out / "tokenizer"
    if (folder / "eval.json").is_file():  # trained by an earlier call of this experiment
        return str(folder)
    tokenizer_config = validate_experiment({**config.to_dict(), "stages": ["tokenizer"]}, host)
    with RunDir.create(tokenizer_config, host=host, path=folder, overwrite=True) as run:
        outcome = run_stage("tokenizer", Assembly(tokenizer_config, host), run)
    if outcome.status != "ran":
        raise stage_failure(outcome)
    return str(folder)


def evaluate_generation_experiment(
    config: Any,
    host: PluginHost,
    out: Path,
    *,
    seeds: list[int],
    n: int,
    tokenizer: str | None = None,
    overwrite: bool = False,
    distribution: bool = True,
    report: Any = print,
) -> dict[str, Any]:
    """Train a generator per seed over one tokenizer, score every conditioner against the baselines;
    write generation.json/.md/.png into ``out`` (see the module docstring).  ``distribution=False``
    leaves out ``fd_effnetlite0`` and the classifier (EfficientNet-Lite0 at 224 px: the slow part on a CPU)."""
    from .command_handlers import _with_tokenizer_run

    if "generator" not in config.stages or config.generator.model is None:
        raise ConfigError(f"scene {config.scene!r} has no generator; use e.g. --scene tour or label-to-touch")
    if not config.generator.conditioners:
        raise ConfigError("the scene's generator has no conditioners (generator.conditioners) to compare")
    record = ExperimentRecord("generation", out, seeds, overwrite=overwrite)
    base = _with_tokenizer_run(config, _tokenizer_run(config, tokenizer, out, host), host)
    rows: list[dict[str, Any]] = []
    skipped: dict[str, str] = {}
    for seed in record.seeds:
        generation = _seed_generation(base, seed, n, distribution, out, host)
        seed_rows = rows_of(generation, seed)
        rows += seed_rows
        for scores in (generation.get("by_conditioner") or {"": generation}).values():
            skipped |= scores.get("skipped") or {}
        report(
            f"seed {seed}: "
            + ", ".join(
                f"{row['conditioner']} contact PSNR {row.get('contact_psnr', '-')}"
                for row in seed_rows
                if row["method"] == "generator"
            )
        )
    keys = in_column_order(key for row in rows for key in row if key not in ("conditioner", "method", "seed"))
    summary = mean_spread(rows, keys, ("conditioner", "method"))
    result = {
        "scene": config.scene,
        "tokenizer": base.generator.tokenizer_run,
        "n": n,
        "generator_steps": base.generator.train.steps,
        "sampling_steps": base.generator.steps,
        "sampler": base.generator.sampler.name if base.generator.sampler else None,
        "rows": rows,
        "summary": summary,
        "skipped": skipped,
    }
    lines = _markdown(result, keys, len(record.seeds))
    plot(
        summary,
        record.path("generation.png"),
        f"generation per conditioner ({len(record.seeds)} seeds, {result['generator_steps']} training steps)",
    )
    record.write(result, lines)
    return result


def _seed_generation(base: Any, seed: int, n: int, distribution: bool, out: Path, host: PluginHost) -> dict[str, Any]:
    """Train the generator of ``seed`` into ``out``/seed<S>, scoring ``n`` held-out conditions; its generation.json."""
    data = base.to_dict()
    data["seed"] = seed
    data["generator"] |= {"num_samples": n, "distribution": distribution}
    seed_config = validate_experiment(data, host)
    with RunDir.create(seed_config, host=host, path=out / f"seed{seed}", overwrite=True) as run:
        outcome = run_stage("generator", Assembly(seed_config, host), run)
        if outcome.status != "ran":
            raise stage_failure(outcome)
        return json.loads((run.path / "generation.json").read_text())


def _markdown(result: dict[str, Any], keys: list[str], seeds: int) -> list[str]:
    """generation.md: the table of ``result``'s summary (mean ± std over ``seeds``), the verdicts, what was skipped."""
    summary, skipped = result["summary"], result["skipped"]
    lines = [
        f"# Generation per conditioner ({seeds} seeds: mean ± std)",
        "",
        f"Scene `{result['scene']}`; tokenizer `{result['tokenizer']}`; one generator per seed trained "
        f"{result['generator_steps']} steps with every conditioner; {result['n']} held-out conditions generated "
        f"with `{result['sampler']}`, {result['sampling_steps']} steps, unguided.  Arrows: "
        + ", ".join(f"{key} {direction_arrow(key)}" for key in keys)
        + ".",
        "",
        *markdown_table(summary, ("conditioner", "method"), keys),
        "",
        "Verdicts (contact region only, a gap counts when it exceeds both spreads):",
        "",
        *(verdicts(summary) or ["- no contact-region score to compare"]),
    ]
    if skipped:
        lines += ["", "Skipped: " + "; ".join(f"`{name}`: {reason}" for name, reason in sorted(skipped.items()))]
    return lines

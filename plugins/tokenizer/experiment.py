"""``vqtouch evaluate reconstruction --out DIR``: the paper's Table 1, reconstruction against training-set size.

::

    vqtouch evaluate reconstruction --out runs/exp/reconstruction [--scene reconstruction] \\
        [--samples 100 1000 10000] [--models vqgan dm_vqgan] [--mae-ratios 0.25 0.5 0.75] \\
        [--held-out 200] [--seeds 0 1 2] [--set tokenizer.train.steps=300 ...]

For every seed, training-set size N (``--samples``) and model, the scene's tokenizer stage trains
one tokenizer on N training samples (``data.train_samples``: with one seed, the 100 are among the
1,000, which are among the 10,000) for the scene's ``tokenizer.train.steps``, the same for every N,
and scores it on the same held-out images.  The models are the scene's tokenizer with each
autoencoder of ``--models`` swapped in (quantizer, discriminator and objective unchanged), and the
MAE baseline at each mask ratio of ``--mae-ratios`` (identity quantizer, no GAN: it is the
continuous, non-tokenizing reference).

Every row carries what the tokenizer stage scores (SSIM, PSNR, MS-SSIM, LPIPS when its weights are
there, reported as skipped otherwise, ``fd_effnetlite0`` unless ``--no-distribution``), the same
scores of the data's no-contact image (what a tokenizer that draws only the background gets),
the contact-region scores (``contact_psnr``, ``contact_ssim``, ``contact_mae``), codebook usage and
the wall time.  Verdicts compare contact PSNR only, and only when a gap exceeds both spreads.

Data: on the embedded procedural scenes the dataset holds max(N) + ``--held-out`` samples and the
held-out split is exactly ``--held-out`` of them; on a reader's dataset (``--set
'data.dataset={"name": "image_folder", "root": ...}'``) the held-out split is the scene's
``data.val_fraction`` of whole recordings/objects, and an N the training split cannot hold is
refused before anything trains.  The seed sets the split, the N-sample draw, the initialisation and
the data order; the models of one seed see the same images.

Written into ``--out``: ``reconstruction.json`` (every row, the mean ± std summary, provenance),
``reconstruction.md`` (the table and verdicts), ``reconstruction.png`` (contact PSNR and SSIM
against N per model, the background as a line) and ``reconstruction_samples.png`` (held-out
images above each model's reconstruction at the largest N, first seed).  Each run keeps its own
folder ``runs/<model>-<N>/seed<S>``; running the command again reuses every finished run whose
config is unchanged, so an interrupted experiment continues where it stopped.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Sequence

from vqtouch.core import Assembly, ConfigError, PluginHost, VqtouchError
from vqtouch.plugins.runtime.execution import run_stage
from vqtouch.plugins.runtime.run_dir import RunDir
from vqtouch.plugins.cli.app import stage_failure
from vqtouch.core.config import validate_experiment
from vqtouch.plugins.utils.splits import experiment_split
from vqtouch.plugins.evaluation.records import (
    ExperimentRecord,
    check_seeds,
    gap_verdict,
    markdown_table,
    mean_spread,
    plot_against_count,
)
from vqtouch.plugins.evaluation.directions import direction_arrow, lower_is_better

#: The columns of the table, in order, when some row has them.
COLUMNS = (
    "ssim",
    "psnr",
    "ms_ssim",
    "lpips",
    "contact_psnr",
    "contact_ssim",
    "contact_mae",
    "fd_effnetlite0",
    "codebook_usage",
    "seconds",
)
#: The no-contact image's copies of those scores (``background_<score>`` in eval.json).
BACKGROUND = "no-contact background"
#: What a finished run keeps beside its eval.json: the experiment's row (wall time included), so a
#: rerun reuses it without training again.
ROW_FILE = "experiment_row.json"


def autoencoder_block(
    scene_block: dict[str, Any] | None, name: str, host: PluginHost, **options: Any
) -> dict[str, Any]:
    """The autoencoder ``name`` with the scene's options that it also has (so ``--set
    tokenizer.autoencoder.channels=32`` holds for every model compared) and ``options``."""
    fields = host.registry("autoencoder").get(name).config_model.model_fields
    kept = {key: value for key, value in (scene_block or {}).items() if key in fields and key != "name"}
    return {"name": name, **kept, **options}


def tokenizer_section(
    scene_section: dict[str, Any], model: str, mask_ratio: float | None, host: PluginHost
) -> dict[str, Any]:
    """The scene's tokenizer section with ``model``'s autoencoder swapped in (quantizer, discriminator
    and objective unchanged), or the MAE baseline at ``mask_ratio`` with the identity quantizer and no
    discriminator (it reconstructs continuously: the non-tokenizing reference)."""
    if mask_ratio is None:
        return scene_section | {"autoencoder": autoencoder_block(scene_section.get("autoencoder"), model, host)}
    return scene_section | {
        "autoencoder": autoencoder_block(None, "mae", host, mask_ratio=mask_ratio),
        "quantizer": {"name": "identity"},
        "discriminator": None,
    }


def model_label(model: str, mask_ratio: float | None) -> str:
    """The model's name in the table (``mae (mask 0.5)`` for the baseline)."""
    return model if mask_ratio is None else f"mae (mask {mask_ratio:g})"


def plan_configs(
    config: Any,
    host: PluginHost,
    *,
    samples: Sequence[int],
    models: Sequence[str],
    mae_ratios: Sequence[float],
    held_out: int | None,
    seed: int,
) -> list[tuple[str, int, Any]]:
    """(model label, N, validated config) of every run of one seed, after checking that the data
    can give each N training samples and the held-out images."""
    base = config.to_dict()
    base["stages"] = ["tokenizer"]
    base["seed"] = seed
    dataset = dict(base["data"]["dataset"] or {})
    if held_out is not None:
        if "num_samples" not in dataset:
            raise ConfigError(
                f"--held-out sets how many procedural samples are held out; the dataset "
                f"{dataset.get('name')!r} holds out data.val_fraction={config.data.val_fraction:g} of "
                "its groups: set that instead"
            )
        total = max(samples) + held_out
        base["data"]["dataset"] = dataset | {"num_samples": total}
        base["data"]["val_fraction"] = held_out / total
    runs = []
    for model, ratio in [(model, None) for model in models] + [("mae", ratio) for ratio in mae_ratios]:
        for count in samples:
            data = json.loads(json.dumps(base))
            data["tokenizer"] = tokenizer_section(data["tokenizer"], model, ratio, host)
            data["data"]["train_samples"] = count
            runs.append((model_label(model, ratio), count, validate_experiment(data, host)))
    _check_sizes(runs, host)
    return runs


def _check_sizes(runs: list[tuple[str, int, Any]], host: PluginHost) -> None:
    """Refuse, before anything trains, an N larger than the training split (one split per seed)."""
    _, count, config = max(runs, key=lambda run: run[1])
    dataset = Assembly(config, host).component("data.dataset")
    largest = len(experiment_split(dataset, config.data.model_copy(update={"train_samples": None}), config.seed)[0])
    if count > largest:
        raise ConfigError(
            f"--samples {count}: the training split of {config.data.dataset.name!r} holds {largest} "
            f"samples ({len(dataset)} in the dataset); use --samples up to {largest}, or more data"
        )


def train_and_score(config: Any, host: PluginHost, folder: Path) -> dict[str, Any]:
    """Train the tokenizer of ``config`` in ``folder`` and return its eval.json with the wall time,
    or the row a finished run with the same config left there."""
    row_file = folder / ROW_FILE
    if row_file.is_file() and (folder / "config.json").is_file():
        try:
            same = RunDir.open(folder).load_config(host).to_dict() == config.to_dict()
        except VqtouchError:  # a damaged or foreign folder is trained again, never trusted
            same = False
        if same:
            return json.loads(row_file.read_text()) | {"reused": True}
    tic = time.perf_counter()
    with RunDir.create(config, host=host, path=folder, overwrite=True) as run:
        outcome = run_stage("tokenizer", Assembly(config, host), run)
        if outcome.status != "ran":
            raise stage_failure(outcome)
        scores = json.loads((run.path / "eval.json").read_text())
    scores["seconds"] = round(time.perf_counter() - tic, 2)
    row_file.write_text(json.dumps(scores, indent=2) + "\n")
    return scores


def rows_of(scores: dict[str, Any], model: str, count: int, seed: int) -> list[dict[str, Any]]:
    """The model's row and the no-contact image's row (scores without their ``background_`` prefix)."""
    keys = [key for key in COLUMNS if isinstance(scores.get(key), (int, float))]
    rows = [{"model": model, "samples": count, "seed": seed, **{key: scores[key] for key in keys}}]
    background = {
        key: scores[f"background_{key}"] for key in COLUMNS if isinstance(scores.get(f"background_{key}"), (int, float))
    }
    if background:
        rows.append({"model": BACKGROUND, "samples": count, "seed": seed, **background})
    return rows


def verdict_lines(summary: list[dict[str, Any]], key: str = "contact_psnr") -> list[str]:
    """Per N: the best model on ``key`` against every other model and against the no-contact image."""
    lines = []
    for count in dict.fromkeys(row["samples"] for row in summary):
        rows = [row for row in summary if row["samples"] == count and key in row]
        sign = 1 if lower_is_better(key) else -1  # best first
        models = sorted((row for row in rows if row["model"] != BACKGROUND), key=lambda row: sign * row[key])
        background = next((row for row in rows if row["model"] == BACKGROUND), None)
        if not models:
            continue
        best = models[0]
        for rival in models[1:] + ([background] if background else []):
            verdict = gap_verdict(best, rival, key, f"`{rival['model']}`")
            lines.append(f"- N = {count}: `{best['model']}` {verdict} on {key}.")
    return lines


def sample_grid(folders: list[tuple[str, Path]], config: Any, host: PluginHost, path: Path, count: int = 8) -> None:
    """The first ``count`` held-out images (top row) above each run's reconstructions of them."""
    import torch

    from vqtouch.plugins.utils.images import image_grid, save_png

    from .stages import load_tokenizer, reconstruct_all

    dataset = Assembly(config, host).component("data.dataset")
    held_out = experiment_split(dataset, config.data, config.seed)[1]
    originals = torch.stack([held_out[index]["tactile"] for index in range(min(count, len(held_out)))])
    rows = [originals]
    for _, folder in folders:
        tokenizer, _ = load_tokenizer(folder, host)
        rows.append(reconstruct_all(tokenizer, originals).cpu())
    save_png(image_grid(torch.cat(rows), columns=len(originals)), path)


def _checked_config(
    config: Any,
    host: PluginHost,
    out: Path,
    *,
    samples: Sequence[int],
    models: Sequence[str],
    mae_ratios: Sequence[float],
    distribution: bool,
    overwrite: bool,
) -> Any:
    """Refuse options that compare nothing or would overwrite ``out``; the config with
    ``fd_effnetlite0`` among its metrics when ``distribution`` asks for it."""
    if not samples:
        raise ConfigError("--samples needs at least one training-set size, e.g. --samples 100 1000")
    if not models and not mae_ratios:
        raise ConfigError("nothing to compare: give --models and/or --mae-ratios")
    if (out / "reconstruction.json").is_file() and not overwrite:
        raise ConfigError(
            f"{out} already holds a reconstruction experiment; pass --overwrite to write it again "
            "(finished runs with an unchanged config are reused), or choose another --out"
        )
    if distribution and not any(item.name == "fd_effnetlite0" for item in config.metrics):
        config = validate_experiment(
            config.to_dict() | {"metrics": [*config.to_dict()["metrics"], {"name": "fd_effnetlite0"}]}, host
        )
    return config


def _run_folder(out: Path, label: str, count: int, seed: int) -> Path:
    """The folder of one run: ``runs/<model>-<N>/seed<S>`` (the label without spaces or brackets)."""
    return out / "runs" / f"{label.replace(' ', '').replace('(', '-').replace(')', '')}-{count}" / f"seed{seed}"


def _run_all(
    plans: dict[int, list[tuple[str, int, Any]]],
    host: PluginHost,
    out: Path,
    seeds: Sequence[int],
    largest: int,
    report: Any,
) -> tuple[list[dict[str, Any]], dict[str, str], list[tuple[str, Path]], Any]:
    """Train and score every planned run: the rows, what was skipped, and the (label, folder) runs of
    the first seed at the ``largest`` N with the config of the last of them (for the sample grid)."""
    rows: list[dict[str, Any]] = []
    skipped: dict[str, str] = {}
    background_rows: set[tuple[int, int]] = set()
    first_runs: list[tuple[str, Path]] = []
    first_config = None
    for seed in seeds:
        for label, count, run_config in plans[seed]:
            folder = _run_folder(out, label, count, seed)
            scores = train_and_score(run_config, host, folder)
            skipped |= scores.get("skipped") or {}
            # The no-contact image's scores depend on the held-out images only: one row per seed and N.
            rows += [
                row
                for row in rows_of(scores, label, count, seed)
                if row["model"] != BACKGROUND or (seed, count) not in background_rows
            ]
            background_rows.add((seed, count))
            report(
                f"seed {seed}: {label}, {count} samples: SSIM {scores.get('ssim')}, contact PSNR "
                f"{scores.get('contact_psnr')} (background {scores.get('background_contact_psnr')})"
                + (" [reused]" if scores.get("reused") else f" in {scores['seconds']:.0f} s")
            )
            if seed == seeds[0] and count == largest:
                first_runs.append((label, folder))
                first_config = run_config
    return rows, skipped, first_runs, first_config


def _markdown_lines(
    config: Any, result: dict[str, Any], keys: list[str], seed_count: int, held_out: int | None
) -> list[str]:
    """reconstruction.md: the heading, the mean ± std table, the verdicts and what was skipped."""
    summary, skipped = result["summary"], result["skipped"]
    lines = [
        f"# Reconstruction against training-set size ({seed_count} seeds: mean ± std)",
        "",
        f"Scene `{config.scene}`, dataset `{result['dataset']}`, {config.data.image_size} px; every tokenizer "
        f"trained {result['steps']} steps on N samples and scored on the same held-out images "
        f"({held_out if held_out is not None else f'data.val_fraction={config.data.val_fraction:g}'}).  "
        "`seconds`: training and scoring wall time.  Arrows: "
        + ", ".join(f"{key} {direction_arrow(key)}" for key in keys if key != "seconds")
        + ".",
        "",
        *markdown_table(summary, ("model", "samples"), keys),
        "",
        "Verdicts (contact region only; a gap counts when it exceeds both spreads):",
        "",
        *(verdict_lines(summary) or ["- no contact-region score to compare"]),
    ]
    if skipped:
        lines += ["", "Skipped: " + "; ".join(f"`{name}`: {reason}" for name, reason in sorted(skipped.items()))]
    return lines


def _write_figures(
    record: ExperimentRecord,
    summary: list[dict[str, Any]],
    first_runs: list[tuple[str, Path]],
    first_config: Any,
    host: PluginHost,
    steps: int,
    largest: int,
) -> list[str]:
    """Write reconstruction.png and, when there are runs to show, reconstruction_samples.png; the
    markdown lines that describe the sample grid."""
    plot_against_count(
        summary,
        count="samples",
        line="model",
        keys=("contact_psnr", "ssim"),
        path=record.path("reconstruction.png"),
        xlabel="training samples",
        dashed=(BACKGROUND,),
        title=f"reconstruction vs training-set size ({len(record.seeds)} seeds, {steps} steps)",
    )
    if not first_runs:
        return []
    sample_grid(first_runs, first_config, host, record.path("reconstruction_samples.png"))
    return [
        "",
        f"`reconstruction_samples.png`: held-out images (top row), then the reconstructions of "
        f"{', '.join(label for label, _ in first_runs)} (one row each, in that order) at N = "
        f"{largest}, seed {record.seeds[0]}.",
    ]


def evaluate_reconstruction_experiment(
    config: Any,
    host: PluginHost,
    out: Path,
    *,
    seeds: list[int],
    samples: Sequence[int],
    models: Sequence[str],
    mae_ratios: Sequence[float],
    held_out: int | None,
    distribution: bool = True,
    overwrite: bool = False,
    report: Any = print,
) -> dict[str, Any]:
    """Train and score every (seed, N, model); write reconstruction.json/.md/.png and the sample grid
    into ``out`` (see the module docstring).  Returns what reconstruction.json holds."""
    config = _checked_config(
        config,
        host,
        out,
        samples=samples,
        models=models,
        mae_ratios=mae_ratios,
        distribution=distribution,
        overwrite=overwrite,
    )
    samples = sorted(set(samples))
    # Every run's config is planned (and every bad option refused) before the folder is made.
    plans = {
        seed: plan_configs(
            config, host, samples=samples, models=models, mae_ratios=mae_ratios, held_out=held_out, seed=seed
        )
        for seed in check_seeds(seeds)
    }
    record = ExperimentRecord("reconstruction", out, seeds, overwrite=overwrite)
    rows, skipped, first_runs, first_config = _run_all(plans, host, out, record.seeds, samples[-1], report)
    keys = [key for key in COLUMNS if any(key in row for row in rows)]
    summary = mean_spread(rows, keys, ("model", "samples"))
    summary.sort(key=lambda row: (row["samples"], row["model"] == BACKGROUND))
    steps = config.tokenizer.train.steps
    result = {
        "scene": config.scene,
        "samples": samples,
        "models": [*models],
        "mae_ratios": [*mae_ratios],
        "steps": steps,
        "held_out": held_out,
        "image_size": config.data.image_size,
        "dataset": config.data.dataset.name,
        "rows": rows,
        "summary": summary,
        "skipped": skipped,
    }
    lines = _markdown_lines(config, result, keys, len(record.seeds), held_out)
    lines += _write_figures(record, summary, first_runs, first_config, host, steps, samples[-1])
    record.write(result, lines)
    return result

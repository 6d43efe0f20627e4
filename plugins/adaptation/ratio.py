"""``vqtouch evaluate mix-ratio --run FAMILY_RUN --out DIR``: how many family images to mix with each
shot of an unseen sensor, measured two ways in one run.

::

    vqtouch evaluate mix-ratio --run runs/tok --out runs/exp/ratio [--target SPEC] [--shots 50] \\
        [--ratios 0 1 2 5 10] [--steps 200] [--all-images 1000] [--eval-images 64] [--families DIR] \\
        [--seeds 0 1 2] [--overwrite]

VQ-Touch adapts a family tokenizer on the sensor's shots mixed 1:ratio with images of its family.
A fine-tuning batch draws from the mixed set uniformly, so at ratio r only 1 / (1 + r) of what it
sees are the sensor's images: at equal steps a mix sees the sensor less than the shots alone do.
So every ratio is trained twice from the family tokenizer:

- **equal steps**: ``--steps`` fine-tuning steps, whatever the ratio;
- **equal exposures**: ``--steps x (1 + r)`` steps, so that every arm sees the sensor's images as
  often as the shots alone do in ``--steps`` (and the family's r times as often on top).

Beside them, from the same family tokenizer and on the same held-out images of the sensor:
``zero-shot`` (no fine-tuning), ``shots alone`` (ratio 0: both budgets at once), ``all images``
(``--all-images`` of the sensor's images alone, ``--steps`` steps: what the shots stand in for) and
the sensor's ``no-contact background``.  Every arm is scored on the sensor (SSIM, PSNR, the contact
region's PSNR and SSIM, ``fd_effnetlite0``) and on held-out images of the family (what it keeps of
the family: the reason to mix at all).

Writes ``mix_ratio.json`` (every arm x seed row, mean ± std over the seeds, the assignments),
``mix_ratio.md`` (the table, the targets' verdicts and the best ratio per budget), ``mix_ratio.png``
(held-out SSIM and contact PSNR against the ratio for both budgets, and the sensor-against-family
trade) and each arm's adapted tokenizer in ``DIR/seed<S>/<arm>/`` with its ``adapt.json``.  An
interrupted run picks up where it stopped: an arm whose ``adapt.json`` records the same shots,
ratio, steps, seed, family and held-out count is read back, not trained again (``--overwrite``
trains every arm again).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Callable, NamedTuple, Sequence

import torch

from vqtouch.core import ConfigError, PluginHost
from vqtouch.plugins.utils.files import read_model
from vqtouch.core.image_size import ImageSize, size_text
from vqtouch.plugins.evaluation.records import (
    ExperimentRecord,
    check_seeds,
    gap_verdict,
    markdown_table,
    mean_spread,
    refuse_finished,
)
from vqtouch.plugins.data.sensor_folders import folder_of, sensor_folder_files

from .adapt import ADAPT_JSON, AdaptRecord, AdaptSettings, adapt_tokenizer
from .adapt_images import sensor_background
from .evaluation import METRICS
from .families import SensorFamilies
from .experiment_inputs import families_for, held_out_count, report_seed_family
from .fewshot import BACKGROUND, SHOTS_ALONE, ZERO_SHOT

ALL_IMAGES = "all images"
STEPS, EXPOSURES, COST = "equal steps", "equal exposures", "equal cost"
#: The held-out scores of an arm on the sensor, and on the family's held-out images.
SCORES = ("ssim", "psnr", "contact_psnr", "contact_ssim", "fd_effnetlite0")
#: What the table shows per arm, in order.
TABLE_COLUMNS = ("steps", "target_views", *SCORES, "family_psnr", "family_ssim", "seconds")
GROUP = ("arm", "budget", "ratio")
#: The ratio trade's tolerance: the best mix within this much SSIM of training on all the sensor's images.
SSIM_TOLERANCE = 0.02


def check_ratios(ratios: Sequence[float]) -> list[float]:
    """``ratios`` ascending, refusing an empty list, a repeat, a negative or non-finite ratio, or a
    list without a mix (every ratio 0)."""
    ratios = [float(r) for r in ratios]
    text = " ".join(f"{r:g}" for r in ratios)
    if not ratios or any(not math.isfinite(r) or r < 0 for r in ratios):
        raise ConfigError(
            f"--ratios {text}: give finite ratios >= 0 (family images per shot), e.g. --ratios 0 1 2 5 10"
        )
    if len(set(ratios)) != len(ratios):
        raise ConfigError(f"--ratios {text} repeats a ratio; give distinct ratios")
    if max(ratios) == 0:
        raise ConfigError(f"--ratios {text}: add at least one ratio > 0 (a mix) to compare with the shots alone")
    return sorted(ratios)


def exposure_steps(steps: int, ratio: float) -> int:
    """Steps at which a 1:``ratio`` mix sees the sensor's images as often as the shots alone do in
    ``steps`` (a batch draws uniformly from the mixed set: 1 / (1 + ratio) of it is the sensor's)."""
    return max(1, round(steps * (1 + ratio)))


class Arm(NamedTuple):
    """One fine-tuned arm: its name, the budget it is shown under, its folder in ``seed<S>/``, the
    family images per shot, the sensor images it learns from and its steps."""

    name: str
    budget: str
    folder: str
    ratio: float
    images: int
    steps: int


def arm_plan(
    shots: int, ratios: Sequence[float], steps: int, cost_controls: Sequence[float], all_images: int
) -> list[Arm]:
    """Every seed's arms, in the table's order: the shots alone (ratio 0, both budgets at once), each
    mix at equal steps and at equal exposures, the shots alone as long as each ``cost_controls``
    mix, and all images."""
    mixes = [ratio for ratio in ratios if ratio > 0]
    plan = [Arm(SHOTS_ALONE, "both", "shots", 0.0, shots, steps)]
    plan += [Arm(f"mixed 1:{r:g}, {STEPS}", STEPS, f"mixed-{r:g}-steps", r, shots, steps) for r in mixes]
    plan += [
        Arm(f"mixed 1:{r:g}, {EXPOSURES}", EXPOSURES, f"mixed-{r:g}-exposures", r, shots, exposure_steps(steps, r))
        for r in mixes
    ]
    for ratio in cost_controls:
        long = exposure_steps(steps, ratio)
        plan.append(Arm(f"{SHOTS_ALONE}, {long} steps", COST, f"shots-{long}", 0.0, shots, long))
    return plan + [Arm(ALL_IMAGES, "-", "all", 0.0, all_images, steps)]


def _differences(summary: dict[str, Any], settings: AdaptSettings) -> dict[str, Any]:
    """How an ``adapt.json`` already in an arm's folder differs from this arm (shots, ratio, steps,
    seed, family, held-out images and fine-tuned part): ``{key: (recorded, wanted)}``."""
    wanted = {
        "shots": settings.shots,
        "ratio": settings.ratio,
        "steps": settings.steps,
        "seed": settings.seed,
        "family": settings.family,
        "held_out": settings.eval_images,
        "part": settings.part,
    }
    return {key: (summary.get(key), value) for key, value in wanted.items() if summary.get(key) != value}


def adapt_arm(
    run: Any,
    target: str,
    families: SensorFamilies,
    host: PluginHost,
    out: Path,
    settings: AdaptSettings,
    background_3HW: torch.Tensor,
    *,
    resume: bool,
) -> tuple[dict[str, Any], bool]:
    """One arm's ``adapt.json`` summary: read back from ``out`` when ``resume`` and it is this arm's,
    otherwise adapted now.  Returns it and whether it was read back.  A finished arm with other
    settings is refused unless ``resume`` is off (``--overwrite``)."""
    path = out / ADAPT_JSON
    if resume and path.is_file():
        summary = read_model(path, AdaptRecord).model_dump()
        differing = _differences(summary, settings)
        if not differing:
            return summary, True
        said = ", ".join(f"{key} {old!r} (now {new!r})" for key, (old, new) in differing.items())
        raise ConfigError(
            f"{out} holds a finished arm with other settings: {said}; pass --overwrite to train every arm "
            "again, or choose another --out"
        )
    summary = adapt_tokenizer(
        run,
        target,
        families,
        host,
        out,
        settings,
        overwrite=True,
        report=lambda line: None,
        background_3HW=background_3HW,
    )
    return summary, False


def _row(
    arm: str, budget: str, ratio: float, seed: int, summary: dict[str, Any], *, after: bool = True
) -> dict[str, Any]:
    when = "after" if after else "before"
    scores, family = summary[when], summary["family_held_out"][when]
    steps = summary["steps"] if after else 0
    shots, family_images = summary["shots"], summary["family_images"] if after else 0
    return {
        "arm": arm,
        "budget": budget,
        "ratio": ratio,
        "seed": seed,
        "steps": steps,
        # Expected sensor images seen: a batch draws uniformly from the shots and the family images.
        "target_views": round(steps * summary["batch_size"] * shots / (shots + family_images)) if after else 0,
        "train_images": shots + family_images if after else 0,
        **{key: scores[key] for key in SCORES if key in scores},
        "family_ssim": family["ssim"],
        "family_psnr": family["psnr"],
        "seconds": summary["seconds"] if after else 0.0,
    }


def all_images_count(target: str, shots: int, all_images: int, eval_images: int, host: PluginHost) -> tuple[int, int]:
    """(all-images arm's image count, held-out count): for a folder, every image not held out (at
    least the shots), with the held-out images the shots leave (``eval_images`` at most)."""
    if folder_of(target) is None:
        return all_images, eval_images
    held_out = held_out_count(target, [shots], eval_images, host, flag="--shots")
    available = len(sensor_folder_files(folder_of(target), host)) - held_out
    return min(all_images, available), held_out


def evaluate_mix_ratio(
    run: str | Path,
    host: PluginHost,
    out: str | Path,
    *,
    target: str,
    seeds: Sequence[int],
    shots: int = 50,
    ratios: Sequence[float] = (0, 1, 2, 5, 10),
    steps: int = 200,
    all_images: int = 1000,
    eval_images: int = 64,
    families: str | Path | None = None,
    cost_controls: Sequence[float] = (),
    overwrite: bool = False,
    report: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Run the experiment of the module docstring and write its files into ``out``; returns what
    ``mix_ratio.json`` holds.  ``cost_controls``: mix ratios whose equal-exposure step count the
    shots alone also train for (``shots alone, N steps``): an equal-exposure mix trains longer, and
    this arm tells the longer training from the mix.  Every bad input is refused with a one-line
    ConfigError before anything trains."""
    from vqtouch.plugins.runtime.run_dir import RunDir
    from vqtouch.plugins.tokenizer import load_tokenizer

    out = Path(out)
    refuse_finished(out, "mix_ratio", "a mix-ratio experiment", overwrite)
    seeds = check_seeds(seeds)
    ratios = check_ratios(ratios)
    cost_controls = sorted({float(ratio) for ratio in cost_controls})
    _check_cost_controls(cost_controls, ratios)
    _check_sizes_and_run(run, shots, steps, all_images, eval_images)
    config = RunDir.open(run).load_config(host)
    tokenizer, folder = load_tokenizer(run, host)
    image_size: ImageSize = tokenizer.autoencoder.vqtouch_spec.context.image_size
    all_images, held_out = all_images_count(target, shots, all_images, eval_images, host)
    # One batch for every arm, fine-tuning and scoring: the contact region's noise estimate is made per
    # batch, so the arms' regions are the same pixels only when their batches are.
    batch_size = min(config.data.batch_size, shots)
    background, background_source = sensor_background(target, host, image_size)
    record = ExperimentRecord("mix_ratio", out, seeds, overwrite=overwrite)
    fitted, families_source = families_for(families, tokenizer, folder, target, host, out, image_size)
    plan = arm_plan(shots, ratios, steps, cost_controls, all_images)
    inputs = _ArmInputs(run, target, fitted, host, out, held_out, batch_size, background, resume=not overwrite)
    rows, skipped, assignments, name, source = _run_seeds(
        inputs, tokenizer, record.seeds, plan, shots, image_size, report
    )
    summary_rows = mean_spread(rows, (*TABLE_COLUMNS, "train_images"), GROUP)
    result = {
        "run": str(run),
        "tokenizer": str(folder),
        "target": name,
        "target_source": source,
        "background": background_source,
        "image_size": image_size,
        "shots": shots,
        "ratios": ratios,
        "cost_controls": cost_controls,
        "steps": steps,
        "all_images": all_images,
        "batch_size": batch_size,
        "held_out": held_out,
        "families": families_source,
        "assignments": assignments,
        "rows": rows,
        "summary": summary_rows,
        "best": best_settings(summary_rows),
        "skipped": skipped,
    }
    plot_mix_ratio(summary_rows, record.path("mix_ratio.png"), f"{name}: {shots} shots, {len(record.seeds)} seed(s)")
    record.write(result, render_markdown(result))
    return result


def _check_cost_controls(cost_controls: list[float], ratios: list[float]) -> None:
    """Refuse a cost control that is no mix ratio of ``ratios``."""
    stray = [ratio for ratio in cost_controls if ratio == 0 or ratio not in ratios]
    if stray:
        raise ConfigError(
            f"--cost-controls {' '.join(f'{r:g}' for r in stray)}: name mix ratios of --ratios "
            f"({' '.join(f'{r:g}' for r in ratios if r > 0)})"
        )


def _check_sizes_and_run(run: str | Path, shots: int, steps: int, all_images: int, eval_images: int) -> None:
    """Refuse counts below their minimum, and a ``run`` that is no run directory."""
    if shots < 1 or steps < 1 or all_images < 1 or eval_images < 2:
        raise ConfigError(
            f"--shots {shots}, --steps {steps}, --all-images {all_images}, --eval-images {eval_images}: "
            "shots, steps and all-images must be >= 1, eval-images >= 2"
        )
    if not (run and (Path(run) / "config.json").is_file()):
        raise ConfigError(f"--run {run}: not a run directory (no config.json); give the family tokenizer's run")


class _ArmInputs(NamedTuple):
    """What every arm of every seed adapts with (:func:`adapt_arm`)."""

    run: str | Path
    target: str
    families: SensorFamilies
    host: PluginHost
    out: Path
    held_out: int
    batch_size: int
    background_3HW: torch.Tensor
    resume: bool


def _run_seeds(
    inputs: _ArmInputs,
    tokenizer: Any,
    seeds: Sequence[int],
    plan: list[Arm],
    shots: int,
    image_size: ImageSize,
    report: Callable[[str], None],
) -> tuple[list[dict[str, Any]], dict[str, str], list[dict[str, Any]], str, str]:
    """Every seed's family and every arm of ``plan`` adapted from it: the rows, the metrics skipped, the
    assignments, and the sensor's name and source."""
    rows: list[dict[str, Any]] = []
    assignments, skipped = [], {}
    name = source = ""
    for seed in seeds:
        name, source, assignment = report_seed_family(
            inputs.families,
            tokenizer,
            inputs.target,
            inputs.host,
            shots=shots,
            eval_images=inputs.held_out,
            image_size=image_size,
            seed=seed,
            report=report,
        )
        assignments.append(assignment)
        for arm in plan:
            settings = AdaptSettings(
                shots=arm.images,
                ratio=arm.ratio,
                steps=arm.steps,
                eval_images=inputs.held_out,
                seed=seed,
                family=assignment["family"],
                batch_size=inputs.batch_size,
                metrics=METRICS,
            )
            summary, reused = adapt_arm(
                inputs.run,
                inputs.target,
                inputs.families,
                inputs.host,
                inputs.out / f"seed{seed}" / arm.folder,
                settings,
                inputs.background_3HW,
                resume=inputs.resume,
            )
            if arm.name == SHOTS_ALONE:  # the family tokenizer before fine-tuning, and the background, once per seed
                rows.append(_row(ZERO_SHOT, "-", 0.0, seed, summary, after=False))
                rows.append(_background_row(seed, summary))
            rows.append(_row(arm.name, arm.budget, arm.ratio, seed, summary))
            skipped |= summary["after"].get("skipped") or {}
            last = rows[-1]
            report(
                f"seed {seed}, {arm.name}: {arm.steps} steps{' (read back)' if reused else ''}, SSIM "
                f"{last.get('ssim')}, contact PSNR {last.get('contact_psnr')}, family PSNR {last.get('family_psnr')}"
            )
    return rows, skipped, assignments, name, source


def _background_row(seed: int, summary: dict[str, Any]) -> dict[str, Any]:
    """The sensor's no-contact background scored against the same held-out images (the
    ``background_*`` scores every arm's summary carries)."""
    before = summary["before"]
    return {
        "arm": BACKGROUND,
        "budget": "-",
        "ratio": 0.0,
        "seed": seed,
        "steps": 0,
        "target_views": 0,
        "train_images": 0,
        **{key: before[f"background_{key}"] for key in SCORES if f"background_{key}" in before},
    }


def best_settings(summary: Sequence[dict[str, Any]], key: str = "ssim") -> dict[str, Any]:
    """Per budget, the ratio (0 included: the shots alone) with the best mean ``key`` on the sensor,
    and among the mixes the one with the best ``key`` that keeps the family at least as well as the
    zero-shot tokenizer (family PSNR)."""
    zero = next((row for row in summary if row["arm"] == ZERO_SHOT), None)
    best: dict[str, Any] = {}
    for budget in (STEPS, EXPOSURES):
        candidates = [row for row in summary if row["budget"] in (budget, "both") and row.get(key) is not None]
        if not candidates:
            continue
        top = max(candidates, key=lambda row: row[key])
        keeping = [
            row
            for row in candidates
            if row["ratio"] > 0 and zero is not None and (row.get("family_psnr") or -math.inf) >= zero["family_psnr"]
        ]
        best[budget] = {
            "ratio": top["ratio"],
            key: top[key],
            "keeps_family": (
                {"ratio": max(keeping, key=lambda row: row[key])["ratio"], key: max(row[key] for row in keeping)}
                if keeping
                else None
            ),
        }
    return best


def verdict_lines(summary: Sequence[dict[str, Any]], key: str = "ssim") -> list[str]:
    """The ratio trade's two targets at the best mix (ratio > 0, either budget): within
    :data:`SSIM_TOLERANCE` of training on all the sensor's images, and better than the shots alone
    (a gap counts beyond both spreads)."""
    mixes = [row for row in summary if row["ratio"] > 0 and row.get(key) is not None]
    rows = {row["arm"]: row for row in summary}
    if not mixes:
        return ["- no mixed arm scored"]
    top = max(mixes, key=lambda row: row[key])
    lines = []
    if ALL_IMAGES in rows and rows[ALL_IMAGES].get(key) is not None:
        gap = rows[ALL_IMAGES][key] - top[key]
        met = "met" if gap <= SSIM_TOLERANCE else "missed"
        side = "below" if gap >= 0 else "above"
        lines.append(
            f"- The best mix, {top['arm']}, is {abs(gap):.3f} {key} {side} {ALL_IMAGES} "
            f"({top[key]:.4g} against {rows[ALL_IMAGES][key]:.4g}; target: within {SSIM_TOLERANCE} below): {met}."
        )
    rivals = [rows[SHOTS_ALONE]] if SHOTS_ALONE in rows else []
    # The shots alone trained as long as the best mix, when the run has that control: the mix, not the length.
    rivals += [row for row in summary if row["budget"] == COST and row["steps"] == top["steps"]]
    for rival in rivals:
        lines.append(f"- The best mix, {top['arm']}, {gap_verdict(top, rival, key, rival['arm'])} on {key}.")
        if "contact_psnr" in top and "contact_psnr" in rival:
            lines.append(
                f"- On the contact region it {gap_verdict(top, rival, 'contact_psnr', rival['arm'])} (contact PSNR)."
            )
    if top["budget"] == EXPOSURES and not any(rival["budget"] == COST for rival in rivals):
        lines.append(
            f"- {top['arm']} trains {top['steps']} steps: part of its gain over the shots alone may be the longer "
            f"training; `--cost-controls {top['ratio']:g}` trains the shots alone as long."
        )
    return lines


def plot_mix_ratio(summary: Sequence[dict[str, Any]], path: Path, title: str) -> None:
    """Three panels: held-out SSIM and contact PSNR on the sensor against the ratio, one line per
    budget (ratio 0 is the shots alone in both), the zero-shot tokenizer, the all-images arm and
    the background as horizontal lines; and the trade, the sensor's SSIM against the family's
    PSNR, each point labelled with its ratio."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(15, 4.6), dpi=110)
    FigureCanvasAgg(figure)
    panels = [figure.add_subplot(1, 3, index) for index in (1, 2, 3)]
    lines_of = {row["arm"]: row for row in summary if row["budget"] == "-"}
    ratios = sorted({row["ratio"] for row in summary if row["budget"] in (STEPS, EXPOSURES, "both")})
    # Ratios on an even axis (0, 1, 2, 5, 10 are not evenly useful on a linear one), labelled with the ratio.
    position = {ratio: index for index, ratio in enumerate(ratios)}
    for panel, key, label in zip(panels, ("ssim", "contact_psnr"), ("held-out SSIM", "contact PSNR (dB)")):
        for budget, marker in ((STEPS, "o"), (EXPOSURES, "s")):
            points = sorted(
                (row["ratio"], row[key], row.get(f"{key}_std") or 0.0)
                for row in summary
                if row["budget"] in (budget, "both") and row.get(key) is not None
            )
            if points:
                ratios_, ys, errors = zip(*points)
                panel.errorbar([position[r] for r in ratios_], ys, yerr=errors, marker=marker, capsize=3, label=budget)
        base = next((row["steps"] for row in summary if row["arm"] == SHOTS_ALONE), None)
        for row in summary:
            matched = row["steps"] / base - 1 if base and row["budget"] == COST else None
            if matched in position and row.get(key) is not None:
                panel.scatter([position[matched]], [row[key]], marker="^", color="black", zorder=3)
                panel.annotate(
                    f"shots alone\n{row['steps']:.0f} steps",
                    (position[matched], row[key]),
                    textcoords="offset points",
                    xytext=(-48, -4),
                    fontsize=7,
                )
        for arm, style in ((ZERO_SHOT, "--"), (ALL_IMAGES, ":"), (BACKGROUND, "-.")):
            if arm in lines_of and lines_of[arm].get(key) is not None:
                panel.axhline(lines_of[arm][key], linestyle=style, color="grey", linewidth=1)
                panel.annotate(arm, (0, lines_of[arm][key]), fontsize=7, color="grey", va="bottom")
        panel.set_xticks(range(len(ratios)), [f"1:{r:g}" if r else "shots\nalone" for r in ratios])
        panel.set_xlabel("family images per shot")
        panel.set_ylabel(label)
        panel.grid(alpha=0.3)
        panel.legend(fontsize=8)
    trade = panels[2]
    for budget, marker in ((STEPS, "o"), (EXPOSURES, "s")):
        points = sorted(
            (row["ratio"], row["family_psnr"], row["ssim"])
            for row in summary
            if row["budget"] in (budget, "both") and row.get("ssim") is not None and row.get("family_psnr") is not None
        )
        if points:
            _, xs, ys = zip(*points)
            trade.plot(xs, ys, marker=marker, label=budget)
            for ratio, x, y in points:
                trade.annotate(f"{ratio:g}", (x, y), textcoords="offset points", xytext=(4, 3), fontsize=7)
    controls = [row for row in summary if row["budget"] == COST]
    for row in [lines_of.get(ZERO_SHOT), lines_of.get(ALL_IMAGES), *controls]:
        if row and row.get("family_psnr") is not None and row.get("ssim") is not None:
            marker = {ZERO_SHOT: "x", ALL_IMAGES: "*"}.get(row["arm"], "^")
            label = row["arm"] if row["budget"] != COST else f"{SHOTS_ALONE}, {row['steps']:.0f} steps"
            trade.scatter([row["family_psnr"]], [row["ssim"]], marker=marker, color="black", label=label, zorder=3)
    trade.set_xlabel("family held-out PSNR (dB): what it keeps of the family")
    trade.set_ylabel("unseen sensor held-out SSIM")
    trade.grid(alpha=0.3)
    trade.legend(fontsize=8)
    figure.suptitle(title, fontsize=9)
    figure.tight_layout()
    figure.savefig(path)


def render_markdown(result: dict[str, Any]) -> list[str]:
    """The table, the targets' verdicts and the best ratio per budget of ``mix_ratio.json``."""
    shots, steps = result["shots"], result["steps"]
    lines = [
        f"# How many family images per shot ({len(result['assignments'])} seed(s): mean ± std)",
        "",
        f"Family tokenizer `{result['tokenizer']}`, {size_text(result['image_size'])} px; unseen sensor "
        f"`{result['target']}`, {shots} shots, batch {result['batch_size']}.  `{STEPS}`: {steps} fine-tuning "
        f"steps at every ratio; `{EXPOSURES}`: {steps} x (1 + ratio) steps, so every arm sees the sensor's "
        f"images as often as `{SHOTS_ALONE}` does (`target_views`: sensor images seen, expected); "
        f"`{ALL_IMAGES}`: {result['all_images']} of the sensor's images alone, {steps} steps.  Every arm scores "
        f"the same {result['held_out']} held-out images of the sensor; `contact_*` on the contact region only; "
        "`family_*` on held-out images of the family (what an arm keeps of it).  "
        f"`{BACKGROUND}`: {result['background']}.",
        "",
        *markdown_table(result["summary"], GROUP, TABLE_COLUMNS, {"target_views": "sensor images seen"}),
        "",
        "Targets (SSIM on the sensor's held-out images; a gap over the shots alone counts beyond both spreads):",
        "",
        *verdict_lines(result["summary"]),
        "",
        "Best ratio per budget (SSIM on the sensor; and the best mix that keeps the family at least as well as "
        "the zero-shot tokenizer):",
        "",
    ]
    for budget, best in result["best"].items():
        keeping = best["keeps_family"]
        lines.append(
            f"- {budget}: best {_ratio_text(best['ratio'])} (SSIM {best['ssim']:.4g}); keeping the family: "
            + (f"{_ratio_text(keeping['ratio'])} (SSIM {keeping['ssim']:.4g})" if keeping else "no mix")
            + "."
        )
    lines += [
        "",
        "Families: "
        + result["families"]
        + "; "
        + "; ".join(
            f"seed {entry['seed']}: family {entry['family']} ({', '.join(entry['members'])})"
            + (" (nearest; assignment refused)" if entry["refused"] else "")
            for entry in result["assignments"]
        )
        + ".",
    ]
    if result["skipped"]:
        lines += ["", "Skipped: " + "; ".join(f"`{k}`: {v}" for k, v in sorted(result["skipped"].items()))]
    return lines


def _ratio_text(ratio: float) -> str:
    return "the shots alone" if ratio == 0 else f"1:{ratio:g}"

"""``vqtouch demo``: run a scene end to end with what is installed and write a report.

The demo runs each stage of the scene (scaled down unless ``--full``), then reports on
every component the stages need: its size, a bit-for-bit checkpoint round trip, and what
it does (a sensor's render, a metric's sanity scores, a dataset's preview).  A stage that
cannot run says why; nothing is faked.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import sys
import time
from pathlib import Path
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import torch
from pydantic import Field
from torch import nn

from vqtouch.core.assembly import Assembly
from vqtouch.core.checkpoint import atomic_write, load, save
from vqtouch.core.components import Metric, SensorFamily, TactileDataset
from vqtouch.core.config import ExperimentConfig, scale_for_demo, validate_experiment  # noqa: F401 - re-exported
from vqtouch.core.errors import ConfigError, VqtouchError
from vqtouch.plugins.utils.files import FileModel, check_model
from vqtouch.core.image_size import ImageSize, image_hw, pixel_centres_mm
from vqtouch.plugins.utils.images import image_grid, save_png
from vqtouch.plugins.utils.progress import progress
from vqtouch.plugins.runtime.run_dir import RunDir, read_run_json
from vqtouch.plugins.utils.seeding import make_generator
from vqtouch.core.stages import empty_slot_reason, missing_slots, required_slots
from vqtouch.plugins.runtime.execution import run_stage

from vqtouch.plugins.evaluation.directions import declared_directions, direction_arrow, metric_directions

from .html import render_html
from .results import component_status, format_value, is_skip_key, skipped_groups, skipped_items, stage_parts
from .verdicts import BACKGROUND_PREFIX, beats, contact_verdict, score_table

if TYPE_CHECKING:
    from vqtouch.core.plugin_manager import PluginHost


def _parameter_count(component: Any) -> int:
    return sum(p.numel() for p in component.parameters()) if isinstance(component, nn.Module) else 0


def _roundtrip(component: nn.Module, path: Any, host: PluginHost) -> str:
    save(component, path, step=0, host=host)
    reloaded = load(path, host=host)
    original, restored = component.state_dict(), reloaded.state_dict()
    if set(original) != set(restored) or any(not torch.equal(original[k], restored[k]) for k in original):
        return "MISMATCH"
    return f"ok ({path.stat().st_size / 1024:.1f} KiB)"


def _metric_sanity(metric: Metric, generator: torch.Generator) -> dict[str, float]:
    """Score a smooth synthetic image against itself and against noisy copies (known noise levels)."""
    ys, xs = torch.meshgrid(torch.linspace(0, 1, 64), torch.linspace(0, 1, 64), indexing="ij")
    clean = torch.stack([xs, ys, (xs + ys) / 2]).unsqueeze(0)
    scores = {}
    for sigma in (0.0, 0.01, 0.05, 0.1):
        noisy = (clean + sigma * torch.randn(clean.shape, generator=generator)).clamp(0, 1)
        metric.reset()
        metric.update(noisy, clean)
        scores[f"noise_sigma={sigma}"] = round(metric.compute(), 4)
    return scores


def _ball_presses(image_size: ImageSize, sensor: SensorFamily, radius_mm: float = 2.0) -> torch.Tensor:
    """Height maps (mm) of a 2 mm ball pressed 0.2, 0.5 and 1.0 mm deep at the centre of ``sensor``'s
    imaged area: a sensor-agnostic probe."""
    height, width = image_hw(image_size)
    ys, xs = pixel_centres_mm(height, width, sensor.imaged_extent_mm(height, width))
    ball = (radius_mm**2 - xs**2 - ys**2).clamp_min(0).sqrt()
    return torch.stack([(ball - (radius_mm - depth)).clamp_min(0) for depth in (0.2, 0.5, 1.0)])


def _preview_dataset(dataset: TactileDataset, run: RunDir, slot: str, count: int = 16) -> dict[str, Any]:
    """Save the first samples (tactile | visual) and describe the dataset (speed is measured by bench/)."""
    count = min(count, len(dataset))
    samples = [dataset[index] for index in range(count)]
    images = [image for sample in samples for image in (sample["tactile"], sample.get("visual", sample["tactile"]))]
    path = save_png(image_grid(torch.stack(images), columns=8), run.path / f"preview_{slot.replace('.', '_')}.png")
    labels = [dataset.class_names[s["label"]] for s in samples if s["label"] >= 0 and dataset.class_names]
    return {
        "samples": len(dataset),
        "classes": dataset.num_classes,
        "preview": str(path),
        "first_labels": labels[:8],
        "example_text": samples[0].get("text", ""),
    }


def brief_training_caveat(stage: str, config: ExperimentConfig, host: PluginHost) -> str | None:
    """What the report says at the top of a stage whose model trained no longer than the stage's demo
    cap on its training length (the option its registration names in ``trains``); None otherwise."""
    entry = host.stage(stage)
    if entry.trains is None:
        return None
    value: Any = config.to_dict().get(stage)
    for part in entry.trains.split("."):
        value = value.get(part) if isinstance(value, dict) else None
    if not isinstance(value, int) or value > entry.demo[entry.trains]:
        return None
    return (
        f"Trained for {value} steps ({stage}.{entry.trains}), the demo's length: a model trained this briefly "
        "draws blobs, so these scores show that the stage runs, not what training buys.  Trained results: "
        "docs/results.md; `vqtouch demo --full` trains at the scene's length."
    )


def run_demo(config: ExperimentConfig, host: PluginHost, run: RunDir) -> dict[str, Any]:
    """Run every stage of ``config`` in ``run``, then describe each component the stages need.

    Stages run through :func:`run_stage` with one shared :class:`Assembly`, so every component
    is built once.  Afterwards each required slot is reported: parameters, a bit-for-bit
    checkpoint round trip, a sensor's render of a ball press, a metric's sanity scores, a
    dataset's preview.  The report also holds when the demo started, its wall time (``seconds``, and
    each stage's) and the process's peak resident memory (``peak_rss_mb``).  Returns the report
    (also written as report.json, report.md and report.html).
    """
    start = time.perf_counter()
    assembly = Assembly(config, host)
    report: dict[str, Any] = {
        "scene": config.scene,
        "description": config.description,
        "run_dir": str(run.path),
        "started": _dt.datetime.now().astimezone().isoformat(timespec="seconds"),
        "stages": [],
        "components": [],
    }
    for stage in progress(config.stages, desc="stages", unit="stage"):
        outcome = run_stage(stage, assembly, run)
        entry: dict[str, Any] = {"stage": stage, "status": outcome.describe(), "seconds": round(outcome.seconds, 2)}
        caveat = brief_training_caveat(stage, config, host)
        if caveat is not None and outcome.status == "ran":
            entry["caveat"] = caveat
        if outcome.result is not None:
            entry["result"] = outcome.result
        report["stages"].append(entry)
    generator = make_generator(config.seed)
    for path in required_slots(config, host):
        info = host.slots[path]
        value = config.slot(path)
        if value is None or value == []:
            if path in dict((p, s) for s, p in missing_slots(config, host)):
                report["components"].append(
                    {"slot": path, "plugin": None, "status": f"missing: {empty_slot_reason(path, host)}"}
                )
            continue
        try:
            built = assembly.component(path)
        except VqtouchError as exc:
            names = ", ".join(item.name for item in value) if info.many else value.name
            report["components"].append({"slot": path, "plugin": names, "status": f"skipped: {exc}"})
            continue
        items = list(zip(value, built)) if info.many else [(value, built)]
        for index, (item, component) in enumerate(items):
            slot = f"{path}[{index}]" if info.many else path
            record: dict[str, Any] = {
                "slot": slot,
                "plugin": item.name,
                "status": "built",
                "parameters": _parameter_count(component),
            }
            if isinstance(component, nn.Module):
                record["checkpoint"] = _roundtrip(
                    component, run.checkpoints / f"{slot.replace('.', '_')}.safetensors", host
                )
            if isinstance(component, SensorFamily):
                with torch.no_grad():
                    presses = _ball_presses(config.data.image_size, component)
                    images = component.render(presses, generator=generator)
                record["render"] = str(save_png(image_grid(images), run.path / f"render_{slot}.png"))
            if isinstance(component, Metric):  # the report shows its scores the way the metric declares
                report.setdefault("directions", {}).update(metric_directions({item.name: component}))
            if isinstance(component, Metric) and component.skipped is not None:
                record["status"] = f"skipped: {component.skipped}"
            elif isinstance(component, Metric):
                record["sanity"] = _metric_sanity(component, generator)
            if isinstance(component, TactileDataset):
                record["data"] = _preview_dataset(component, run, slot)
            report["components"].append(record)
    report["seconds"] = round(time.perf_counter() - start, 1)
    report["peak_rss_mb"] = peak_rss_mb()
    run.write_json("report.json", report)
    write_reports(run.path, report)
    return report


def peak_rss_mb() -> float | None:
    """The peak resident memory of this process so far, in MB (2**20 bytes); None where the
    platform does not say (Windows).  Worker processes (``data.num_workers``) are not counted."""
    try:
        import resource
    except ImportError:  # pragma: no cover - Windows
        return None
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return round(peak / (2**20 if sys.platform == "darwin" else 2**10), 1)  # bytes on macOS, KiB on Linux


def write_reports(run_dir: str | Path, report: dict[str, Any], out: str | Path | None = None) -> Path:
    """Write report.md and the self-contained report.html of ``report`` (the run in ``run_dir``, whose
    pictures they embed) into ``out`` (default: the run), atomically; returns report.html's path."""
    run_dir = Path(run_dir)
    target = Path(out) if out is not None else run_dir
    with declared_directions(report.get("directions", {})):
        pages = (("report.md", render_report(report)), ("report.html", render_html(report, run_dir)))
    for name, text in pages:
        atomic_write(target / name, lambda tmp, text=text: tmp.write_text(text, encoding="utf-8"))
    return target / "report.html"


class StageEntry(FileModel):
    """One stage of a ``report.json``."""

    stage: str
    status: str = ""
    seconds: float | None = Field(None, ge=0)
    caveat: str | None = None
    result: dict[str, Any] | None = None


class ComponentEntry(FileModel):
    """One component of a ``report.json`` (its pictures, when it has them, are file names)."""

    slot: str
    status: str = ""
    render: str | None = None
    data: dict[str, Any] | None = None


class ReportRecord(FileModel):
    """What ``vqtouch report`` reads back of a ``report.json``."""

    scene: str = ""
    description: str = ""
    seconds: float | None = Field(None, ge=0)
    peak_rss_mb: float | None = Field(None, ge=0)
    stages: list[StageEntry]
    components: list[ComponentEntry] = []


def rebuild_report(run_dir: str | Path, out: str | Path | None = None) -> Path:
    """``vqtouch report``: rebuild report.md and report.html of a demo run from its report.json (e.g.
    after the renderer changed, or in a copy of the run), in the run or in ``out``; returns report.html's
    path.  A read-only run without ``out`` is refused before anything is rendered."""
    run_dir = Path(run_dir)
    if out is None and run_dir.is_dir() and not os.access(run_dir, os.W_OK):
        raise ConfigError(f"{run_dir} is read-only; give --out DIR for report.html and report.md")
    if not (run_dir / "report.json").is_file():
        what = "no such folder" if not run_dir.exists() else "no report.json in it"
        raise ConfigError(f"{run_dir}: {what}; give the folder of a `vqtouch demo` run (its --out)")
    report = read_run_json(run_dir / "report.json")
    if not isinstance(report, dict) or not isinstance(report.get("stages"), list):
        raise ConfigError(f"{run_dir / 'report.json'}: not a demo report (no list of stages)")
    check_model(report, ReportRecord, run_dir / "report.json")
    if "description" not in report and (run_dir / "config.json").is_file():  # reports written before it was kept
        report["description"] = read_run_json(run_dir / "config.json").get("description", "")
    return write_reports(run_dir, report, out)


#: Marks after a model score in report.md's score tables (explained under each table); unclear: it
#: beats the background but the stage's verdict finds no clear gain.
WORSE_MARK, BETTER_MARK, UNCLEAR_MARK = "✗", "✓", "≈"


def _markdown_scores(table: Any, clear: bool = True) -> list[str]:
    """A stage's scores with comparisons (a :class:`~vqtouch.plugins.report.verdicts.ScoreTable`) as markdown
    table lines: one row per score, the model's column then one per comparison, each model score
    marked by whether it beats the no-contact background (as report.html colours it)."""
    if not table.rows:
        return []
    columns = [prefix.rstrip("_") for prefix in table.columns]
    lines = ["", "| score | model | " + " | ".join(columns) + " |", "|---" * (2 + len(columns)) + "|"]
    for score, values in table.rows.items():
        better = beats(score, values[""], values.get(BACKGROUND_PREFIX))
        mark = "" if better is None else f" {(BETTER_MARK if clear else UNCLEAR_MARK) if better else WORSE_MARK}"
        cells = [
            f"{format_value(values[''])}{mark}",
            *(format_value(values[prefix]) if prefix in values else "-" for prefix in table.columns),
        ]
        lines.append(f"| {score} {direction_arrow(score)} | " + " | ".join(cells) + " |")
    note = "↑ higher is better, ↓ lower is better"
    if BACKGROUND_PREFIX in table.columns:
        note += (
            f"; {BETTER_MARK} the model beats the no-contact background, {WORSE_MARK} it is worse than "
            f"the background (a tie counts as worse), {UNCLEAR_MARK} it beats it but the verdict finds no "
            "clear gain"
        )
    return [*lines, "", f"*{note}.*"]


def _markdown_result(result: Any, title: str) -> list[str]:
    """A stage result (or one of its parts) in markdown: the scores table, the verdict, facts, picture."""
    table = score_table(result)
    # What was skipped is listed once, in the report's Skipped section: here only its names.
    facts = ", ".join(
        f"skipped {', '.join(v) if isinstance(v, Mapping) else 'see Skipped'} (reasons under Skipped)"
        if is_skip_key(k)
        else f"{k} {v:.4g}"
        if isinstance(v, float)
        else f"{k} {v}"
        for k, v in table.facts.items()
    )
    verdict = contact_verdict(result)
    lines = _markdown_scores(table, verdict is None or verdict[0])
    if verdict is not None:
        lines += ["", verdict[1]]
    if facts:
        lines += ["", facts]
    if "picture" in result:
        lines += ["", f"![{title}]({result['picture']})"]
        if result.get("caption"):
            lines += ["", f"*{result['caption']}*"]
    return lines


def render_report(report: dict[str, Any]) -> str:
    """The human-readable report.md (report.html shows the same with its pictures embedded)."""
    lines = [f"# vqtouch demo: scene `{report['scene']}`", ""]
    if report.get("description"):
        lines += [report["description"], ""]
    if "seconds" in report:
        memory = f", peak memory {report['peak_rss_mb']:,.0f} MB" if report.get("peak_rss_mb") is not None else ""
        lines += [f"Wall time {report['seconds']:.0f} s{memory}.", ""]
    lines += ["## Stages", "", "| stage | status |", "|---|---|"]
    lines += [f"| {s['stage']} | {s['status']} |" for s in report["stages"]]
    for s in report["stages"]:
        if "result" in s:
            lines += ["", f"### {s['stage']}"]
            if s.get("caveat"):
                lines += ["", f"> **Trained briefly.** {s['caveat']}"]
            lines += _markdown_result(s["result"], s["stage"])
            for title, part in stage_parts(s["result"]).items():
                lines += ["", f"#### {title}"]
                lines += _markdown_result(part, f"{s['stage']}: {title}")
    lines += [
        "",
        "## Components",
        "",
        "| slot | plugin | status | parameters | checkpoint round trip |",
        "|---|---|---|---|---|",
    ]
    for c in report["components"]:
        lines.append(
            f"| {c['slot']} | {c['plugin'] or '-'} | {component_status(c)} | {c.get('parameters', '-')} "
            f"| {c.get('checkpoint', '-')} |"
        )
    renders = [c for c in report["components"] if "render" in c]
    if renders:
        lines += ["", "## Sensors (a 2 mm ball pressed 0.2, 0.5 and 1.0 mm deep)", ""]
        lines += [f"- `{c['slot']}` ({c['plugin']}): ![{c['slot']}]({Path(c['render']).name})" for c in renders]
    for c in report["components"]:
        if "data" in c:
            data = c["data"]
            lines += [
                "",
                f"## Data (`{c['slot']}`: {c['plugin']})",
                "",
                f'{data["samples"]} samples, {data["classes"]} classes. Example text: "{data["example_text"]}"',
                "",
                f"![tactile | visual pairs]({Path(data['preview']).name})",
            ]
    sanity = [c for c in report["components"] if "sanity" in c]
    if sanity:
        lines += ["", "## Metric sanity (synthetic 64x64 image vs noisy copies)", ""]
        for c in sanity:
            lines.append(f"- `{c['plugin']}`: {json.dumps(c['sanity'])}")
    grouped = skipped_groups(skipped_items(report))
    lines += ["", f"## Skipped ({len(grouped)})", ""]
    if not grouped:
        lines.append("Nothing was reported as skipped.")
    for (what, reason), places in grouped.items():
        lines.append(f"- **{what}** ({', '.join(places)}): {reason}")
    lines += ["", f"Resolved config: `config.json`; environment: `env.json`; run: `{report['run_dir']}`", ""]
    return "\n".join(lines)

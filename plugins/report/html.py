"""The demo's report as one self-contained HTML page: ``report.html`` next to report.md.

Everything the page shows is inside it: images are base64 ``data:`` URIs, the style sheet is
inline, nothing is fetched and no script runs, so the file can be mailed, archived or opened
offline.  It reads a run folder's report.json (see :func:`vqtouch.plugins.report.demo.run_demo`), the
pictures that report names, the run's metrics.jsonl (the training-loss curves) and env.json.

It knows no stage in particular: a stage's section is built from the
generic keys of its result only (``picture`` with an optional ``caption``, ``pictures``, the
scores, ``skipped``); anything a stage wants said about its picture it says in its ``caption``.

Scores are shown against their comparisons by the key convention alone: ``background_psnr`` beside
``psnr`` is the no-contact background image's PSNR (see
:data:`~vqtouch.plugins.report.verdicts.COMPARISON_PREFIXES`).
Tactile images are mostly static background, so a whole-image score flatters a model that draws
only the background: each model score is coloured by whether it beats the background's, and a
verdict on the contact region (``contact_psnr`` against ``background_contact_psnr``) says whether
the model is better where it matters.
"""

from __future__ import annotations

import base64
import datetime as _dt
import html
import io
import json
import math
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from vqtouch.plugins.evaluation.directions import LOWER_IS_BETTER, direction_arrow, lower_is_better  # noqa: F401

from .results import (
    component_status,
    format_duration,
    format_value,
    is_skip_key,
    is_skip_reason,
    skipped_groups,
    skipped_items,
    stage_parts,
)
from .verdicts import BACKGROUND_PREFIX, COMPARISON_PREFIXES, ScoreTable, beats, contact_verdict, score_table

#: Pictures are scaled up by a whole factor (crisp pixels) up to this width, at most 3 times.
MAX_PICTURE_WIDTH = 1100
MAX_UPSCALE = 3

_MIME_TYPES = {
    ".png": "image/png",
    ".jpg": "image/jpeg",
    ".jpeg": "image/jpeg",
    ".gif": "image/gif",
    ".webp": "image/webp",
}

_STYLE = """
:root { --ink: #1d2330; --muted: #5d6677; --line: #dde2ea; --panel: #f6f8fb; --accent: #2f6fbd; }
* { box-sizing: border-box; }
body { margin: 0; font: 15px/1.45 system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; color: var(--ink);
       background: #fff; }
main { max-width: 1180px; margin: 0 auto; padding: 24px 28px 48px; }
h1 { font-size: 1.7em; margin: 0 0 4px; }
h2 { font-size: 1.25em; margin: 0 0 10px; }
h3 { font-size: 1em; margin: 14px 0 6px; color: var(--muted); }
p.lead { margin: 0 0 14px; color: var(--muted); }
section { border-top: 1px solid var(--line); padding: 18px 0 8px; }
dl.facts { display: grid; grid-template-columns: repeat(auto-fill, minmax(210px, 1fr)); gap: 8px 18px;
           margin: 0 0 18px; padding: 12px 16px; background: var(--panel); border-radius: 6px; }
dl.facts div { min-width: 0; }
dl.facts dt { font-size: 0.78em; text-transform: uppercase; letter-spacing: 0.04em; color: var(--muted); }
dl.facts dd { margin: 0; font-weight: 600; overflow-wrap: anywhere; }
table { border-collapse: collapse; font-size: 0.9em; margin: 0 0 10px; }
th, td { padding: 3px 10px; border-bottom: 1px solid var(--line); text-align: left; vertical-align: top; }
th { background: var(--panel); font-weight: 600; }
td.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
td.muted, span.muted { color: var(--muted); }
table.nested td { border: 0; padding: 0 8px 0 0; }
div.scores { max-width: 500px; }  /* leaves room for the loss curve beside it */
td.better, span.better { background: #dff3e4; color: #17642c; font-weight: 600; }
td.worse, span.worse { background: #fde0df; color: #9b1c1c; font-weight: 600; }
span.better, span.worse { padding: 0 4px; border-radius: 3px; }
span.direction { color: var(--muted); font-size: 0.85em; }
p.legend { font-size: 0.8em; color: var(--muted); margin: 0 0 10px; }
p.verdict { margin: 0 0 8px; padding: 6px 10px; border-left: 4px solid; border-radius: 3px; font-weight: 600; }
p.caveat { background: #fff8e1; border-left: 4px solid #e0a800; padding: 6px 10px; }
p.verdict.better { background: #eef8f0; border-color: #2e8b47; color: #17642c; }
p.verdict.worse { background: #fdf0ef; border-color: #c0392b; color: #9b1c1c; }
.status { display: inline-block; padding: 0 7px; border-radius: 9px; font-size: 0.85em; font-weight: 600; }
.status.ran { background: #dff3e4; color: #17642c; }
.status.unavailable { background: #fff1d6; color: #7a5200; }
.status.failed { background: #fde0df; color: #9b1c1c; }
span.detail { font-size: 0.9rem; font-weight: normal; }
h2 span.detail { color: var(--muted); }
td.bar { width: 180px; }
td.bar span { display: block; height: 9px; border-radius: 4px; background: var(--accent); opacity: 0.75; }
.row { display: flex; flex-wrap: wrap; gap: 8px 28px; align-items: flex-start; }
figure { margin: 4px 0 14px; max-width: 100%; }
figure img { display: block; max-width: 100%; height: auto; border: 1px solid var(--line); }
img.pixelated { image-rendering: pixelated; }
figcaption { font-size: 0.85em; color: var(--muted); margin-top: 4px; max-width: 72ch; }
figcaption code, td code { font-size: 0.95em; }
p.missing { color: #9b1c1c; }
footer { border-top: 1px solid var(--line); margin-top: 18px; padding-top: 10px; font-size: 0.85em;
         color: var(--muted); }
"""


def run_file(run_dir: Path, report: Mapping[str, Any], name: str) -> Path | None:
    """The file a report names, found in ``run_dir``: stages name their pictures relative to the run,
    while the demo's own files are recorded under the folder the run was written to, which may
    since have been moved or copied (to ``run_dir``).  None when it names a file outside the run: the
    report embeds only the run's own files."""
    path, recorded, rebased = Path(name), report.get("run_dir"), []
    if recorded:
        try:
            rebased = [run_dir / path.relative_to(recorded)]
        except ValueError:
            pass
    candidates = [*rebased, path] if path.is_absolute() else [run_dir / path, *rebased]
    inside = [candidate for candidate in candidates if candidate.resolve().is_relative_to(run_dir.resolve())]
    return next((candidate for candidate in inside if candidate.is_file()), inside[0] if inside else None)


def _e(value: Any) -> str:
    return html.escape(str(value), quote=True)


def _figure(path: Path | None, caption: str, source: str) -> str:
    """One picture embedded as a data URI with its caption, or a note saying why it is missing
    (``path`` None: it is outside the run, see :func:`run_file`)."""
    from PIL import Image, UnidentifiedImageError

    if path is None:
        return f'<p class="missing">picture not embedded: {_e(source)} is outside the run folder</p>'
    mime = _MIME_TYPES.get(path.suffix.lower())
    if mime is None:
        return f'<p class="missing">{_e(source)}: not an image format a browser shows</p>'
    try:
        data = path.read_bytes()
        with Image.open(io.BytesIO(data)) as image:
            width, height = image.size
    except FileNotFoundError:
        return f'<p class="missing">picture missing: {_e(source)} (no such file in the run)</p>'
    except (OSError, UnidentifiedImageError) as exc:
        return f'<p class="missing">picture unreadable: {_e(source)} ({_e(exc)})</p>'
    return _img_figure(data, mime, width, height, caption, source)


def _img_figure(
    data: bytes, mime: str, width: int, height: int, caption: str, source: str, upscale: bool = True
) -> str:
    # A whole factor keeps the small tactile tiles' pixels square and sharp.
    scale = max(1, min(MAX_UPSCALE, MAX_PICTURE_WIDTH // max(width, 1))) if upscale else 1
    css_class = ' class="pixelated"' if scale > 1 else ""
    uri = f"data:{mime};base64,{base64.b64encode(data).decode('ascii')}"
    return (
        f'<figure><img{css_class} src="{uri}" alt="{_e(caption or source)}" data-source="{_e(source)}" '
        f'width="{width * scale}" height="{height * scale}">'
        f"<figcaption>{_e(caption)} <code>{_e(source)}</code> ({width}&times;{height} px"
        f"{f', shown {scale}&times;' if scale > 1 else ''})</figcaption></figure>"
    )


def _stage_pictures(result: Mapping[str, Any]) -> Iterator[tuple[str, str]]:
    """(file, caption) of each picture a stage result names: ``picture`` (+ ``caption``) and
    ``pictures`` (a list of files, or ``{file: caption}``)."""
    if result.get("picture"):
        yield str(result["picture"]), str(result.get("caption") or "")
    pictures = result.get("pictures")
    if isinstance(pictures, Mapping):
        yield from ((str(name), str(caption or "")) for name, caption in pictures.items())
    elif isinstance(pictures, (list, tuple)):
        yield from ((str(name), "") for name in pictures)


def _value_cell(value: Any) -> str:
    if isinstance(value, Mapping):
        rows = "".join(f"<tr><td>{_e(key)}</td><td>{_e(format_value(item))}</td></tr>" for key, item in value.items())
        return f'<td><table class="nested">{rows}</table></td>'
    numeric = isinstance(value, (int, float)) and not isinstance(value, bool)
    return f'<td class="num">{_e(format_value(value))}</td>' if numeric else f"<td>{_e(format_value(value))}</td>"


def _direction_text(score: str) -> str:
    return "lower is better" if lower_is_better(score) else "higher is better"


def _column_name(prefix: str) -> str:
    return prefix.rstrip("_")


def _comparison_table(table: ScoreTable, clear: bool = True) -> str:
    """``clear``: the stage's verdict found a clear gain (or gives none); when it did not, a score that
    beats the background is shown uncoloured, as the verdict's "no better within noise" or "ignores
    its input" outweighs it."""
    head = "".join(
        f'<th title="{_e(COMPARISON_PREFIXES[prefix])}">{_e(_column_name(prefix))}</th>' for prefix in table.columns
    )
    rows = []
    for score, values in table.rows.items():
        model, background = values[""], values.get(BACKGROUND_PREFIX)
        better = beats(score, model, background)
        if better is None:
            model_cell = _value_cell(model)
        else:
            # Coloured against the background only: that is the comparison a "better" claim must survive.
            verdict = "better" if better else "worse"
            title = f"{verdict} than the no-contact background ({format_value(background)}; {_direction_text(score)})"
            if better and not clear:
                verdict, title = "unclear", title + "; the verdict below finds no clear gain"
            model_cell = f'<td class="num {verdict}" title="{_e(title)}">{_e(format_value(model))}</td>'
        cells = "".join(
            _value_cell(values[prefix]) if prefix in values else '<td class="num muted">-</td>'
            for prefix in table.columns
        )
        rows.append(
            f'<tr><td>{_e(score)} <span class="direction" title="{_direction_text(score)}">'
            f"{direction_arrow(score)}</span></td>{model_cell}{cells}</tr>"
        )
    return (
        f'<table class="scores comparison"><tr><th>score</th><th title="the model this stage trained">model</th>'
        f"{head}</tr>{''.join(rows)}</table>"
    )


def _comparison_legend(table: ScoreTable) -> str:
    """One line under the comparison table: what the colours and the comparison columns mean."""
    parts = []
    if BACKGROUND_PREFIX in table.columns:
        parts.append(
            '<span class="better">green</span>: the model beats the no-contact background, '
            '<span class="worse">red</span>: it does not (a tie does not); uncoloured: it does, but the verdict '
            "finds no clear gain"
        )
    parts += [f"<b>{_e(_column_name(prefix))}</b>: {_e(COMPARISON_PREFIXES[prefix])}" for prefix in table.columns]
    return f'<p class="legend">{"; ".join(parts)}.</p>'


def _scores_block(result: Mapping[str, Any], skipped: list[tuple[str, str, str]]) -> str:
    """A stage's scores: the comparison table (one row per score, one column per comparison), the
    contact-region verdict and the other facts as a key/value table."""
    table = score_table(result)
    verdict = contact_verdict(result)
    parts = [_comparison_table(table, verdict is None or verdict[0])] if table.rows else []
    if verdict is not None:
        better, sentence = verdict
        parts.append(f'<p class="verdict {"better" if better else "worse"}">{_e(sentence)}</p>')
    if table.rows:
        parts.append(_comparison_legend(table))
    parts.append(_facts_table(table.facts, skipped))
    return f'<div class="scores">{"".join(parts)}</div>' if any(parts) else ""


def _facts_table(facts: Mapping[str, Any], skipped: list[tuple[str, str, str]]) -> str:
    rows = [
        f"<tr><td>{_e(key)}</td>{_value_cell(value)}</tr>"
        for key, value in facts.items()
        if not is_skip_key(key) and not is_skip_reason(value)
    ]
    # The reason is in the Skipped section once; here a pointer keeps the table readable.
    rows += [
        f'<tr><td>{_e(what)}</td><td class="muted">skipped (<a href="#skipped">why</a>)</td></tr>'
        for _, what, _reason in skipped
    ]
    if not rows:
        return ""
    return f'<table class="scores facts"><tr><th>other facts</th><th>value</th></tr>{"".join(rows)}</table>'


def read_losses(run_dir: Path) -> dict[str, dict[str, list[tuple[int, float]]]]:
    """The trainer's ``loss`` and ``val_loss`` lines of the run's metrics.jsonl, by stage:
    ``{stage: {"loss": [(step, value), ...], "val_loss": [...]}}`` sorted by step (lines that
    do not parse, e.g. one cut short by a crash, are left out)."""
    path = run_dir / "metrics.jsonl"
    losses: dict[str, dict[str, list[tuple[int, float]]]] = {}
    if not path.is_file():
        return losses
    for line in path.read_text(encoding="utf-8", errors="replace").splitlines():
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            continue
        if not isinstance(record, dict) or not isinstance(record.get("step"), int):
            continue
        for key in ("loss", "val_loss"):
            value = record.get(key)
            if isinstance(value, (int, float)) and math.isfinite(value):
                losses.setdefault(str(record.get("stage")), {}).setdefault(key, []).append((record["step"], value))
    for curves in losses.values():
        for points in curves.values():
            points.sort()
    return losses


def loss_figure(curves: Mapping[str, list[tuple[int, float]]], title: str) -> Any:
    """The matplotlib Figure of :func:`loss_plot`: the training loss on the left axis and, when
    logged, the held-out ``val_loss`` on a right axis of its own (it is the stage's validation
    measure, which need not be the training loss's quantity or scale)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(5.6, 2.9), dpi=100, layout="constrained")
    FigureCanvasAgg(figure)
    axes = figure.add_subplot(1, 1, 1)
    steps, values = zip(*curves["loss"])
    lines = axes.plot(steps, values, marker="o", markersize=3, linewidth=1.5, label="training loss")
    axes.set_xlabel("step")
    axes.set_ylabel("training loss", color="tab:blue")
    if curves.get("val_loss"):
        held_out = axes.twinx()
        steps, values = zip(*curves["val_loss"])
        lines += held_out.plot(
            steps,
            values,
            marker="s",
            markersize=5,
            linestyle="--",
            color="tab:orange",
            label="held-out val_loss (at checkpoints; right axis)",
        )
        held_out.set_ylabel("held-out val_loss", color="tab:orange")
    axes.set_title(title, fontsize=10)
    axes.grid(alpha=0.3)
    axes.legend(lines, [line.get_label() for line in lines], fontsize=8)
    return figure


def loss_plot(curves: Mapping[str, list[tuple[int, float]]], title: str) -> bytes | None:
    """A PNG of the training loss (and held-out ``val_loss``, on its own axis) against the step, or
    None when fewer than two training points were logged (no curve to draw)."""
    if len(curves.get("loss", [])) < 2:
        return None
    buffer = io.BytesIO()
    loss_figure(curves, title).savefig(buffer, format="png")
    return buffer.getvalue()


def _status_badge(status: str) -> str:
    kind = "ran" if status.startswith("ran") else "unavailable" if status.startswith("cannot run") else "failed"
    label = {"ran": "ran", "unavailable": "cannot run", "failed": "failed"}[kind]
    detail = status.split(":", 1)[1].strip() if kind != "ran" and ":" in status else ""
    badge = f'<span class="status {kind}">{label}</span>'
    return badge + (f' <span class="detail">{_e(detail)}</span>' if detail else "")


def _header(report: Mapping[str, Any], run_dir: Path) -> str:
    env = _read_json_or_empty(run_dir / "env.json")
    facts: list[tuple[str, str]] = [("scene", str(report.get("scene", "-")))]
    started = report.get("started") or env.get("created")
    if started:
        try:
            facts.append(("date", _dt.datetime.fromisoformat(started).strftime("%Y-%m-%d %H:%M %Z").strip()))
        except (TypeError, ValueError):
            facts.append(("date", str(started)))
    if isinstance(report.get("seconds"), (int, float)):
        facts.append(("total wall time", format_duration(report["seconds"])))
    if isinstance(report.get("peak_rss_mb"), (int, float)):
        facts.append(("peak memory (RSS)", f"{report['peak_rss_mb']:,.0f} MB"))
    if env.get("device_name"):
        facts.append(("device", str(env["device_name"])))
    versions = env.get("versions") or {}
    if versions.get("vqtouch") or versions.get("torch"):
        facts.append(("versions", f"vqtouch {versions.get('vqtouch') or '?'}, torch {versions.get('torch') or '?'}"))
    facts.append(("run folder", str(run_dir)))
    items = "".join(f"<div><dt>{_e(name)}</dt><dd>{_e(value)}</dd></div>" for name, value in facts)
    description = report.get("description")
    lead = f'<p class="lead">{_e(description)}</p>' if description else ""
    return f'<header><h1>vqtouch demo: {_e(report.get("scene", ""))}</h1>{lead}<dl class="facts">{items}</dl></header>'


def _read_json_or_empty(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return {}
    return data if isinstance(data, dict) else {}


def _stages_overview(stages: list[Mapping[str, Any]]) -> str:
    longest = max((s["seconds"] for s in stages if isinstance(s.get("seconds"), (int, float))), default=0) or 1
    rows = []
    for entry in stages:
        seconds = entry.get("seconds")
        timed = isinstance(seconds, (int, float))
        bar = f'<span style="width: {100 * seconds / longest:.1f}%"></span>' if timed else ""
        rows.append(
            f'<tr><td><a href="#stage-{_e(entry["stage"])}">{_e(entry["stage"])}</a></td>'
            f"<td>{_status_badge(str(entry.get('status', '')))}</td>"
            f'<td class="num">{format_duration(seconds) if timed else "-"}</td><td class="bar">{bar}</td></tr>'
        )
    return (
        '<section><h2>Stages</h2><table class="stages"><tr><th>stage</th><th>status</th><th>time</th><th></th></tr>'
        f"{''.join(rows)}</table></section>"
    )


def _stage_section(
    entry: Mapping[str, Any],
    report: Mapping[str, Any],
    run_dir: Path,
    losses: Mapping[str, Mapping[str, list[tuple[int, float]]]],
    skipped: list[tuple[str, str, str]],
) -> str:
    stage, result = str(entry["stage"]), entry.get("result") or {}
    status = str(entry.get("status", ""))
    parts = [f'<section id="stage-{_e(stage)}"><h2>{_e(stage)} {_status_badge(status)}</h2>']
    if entry.get("caveat"):
        parts.append(f'<p class="caveat"><b>Trained briefly.</b> {_e(str(entry["caveat"]))}</p>')
    own_skips = [item for item in skipped if item[0] == f"stage {stage}"]
    row = [_scores_block(result, own_skips)]
    curve = loss_plot(losses.get(stage, {}), f"{stage}: loss per logged step (metrics.jsonl)")
    if curve is not None:
        row.append(
            _img_figure(
                curve,
                "image/png",
                *_png_size(curve),
                f"Training loss of the {stage} stage at each logged step"
                + (
                    " and, at each checkpoint, its held-out score val_loss (the stage's own validation "
                    "measure, which need not be the training loss's quantity)"
                    if losses[stage].get("val_loss")
                    else ""
                )
                + ".",
                "metrics.jsonl",
                upscale=False,
            )
        )
    if any(row):
        parts.append(f'<div class="row">{"".join(row)}</div>')
    for name, caption in _stage_pictures(result):
        parts.append(_figure(run_file(run_dir, report, name), caption, name))
    for title, part in stage_parts(result).items():
        parts.append(f"<h3>{_e(title)}</h3>{_scores_block(part, [])}")
        for name, caption in _stage_pictures(part):
            parts.append(_figure(run_file(run_dir, report, name), caption, name))
    parts.append("</section>")
    return "".join(parts)


def _png_size(data: bytes) -> tuple[int, int]:
    # Width and height are the first fields of the IHDR chunk, which always comes first.
    return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")


def _skipped_section(skipped: list[tuple[str, str, str]]) -> str:
    if not skipped:
        return '<section id="skipped"><h2>Skipped</h2><p>Nothing was reported as skipped.</p></section>'
    grouped = skipped_groups(skipped)
    rows = "".join(
        f"<tr><td>{_e(', '.join(places))}</td><td>{_e(what)}</td><td>{_e(reason)}</td></tr>"
        for (what, reason), places in grouped.items()
    )
    return (
        f'<section id="skipped"><h2>Skipped ({len(grouped)})</h2><table class="skipped">'
        f"<tr><th>where</th><th>what</th><th>reason</th></tr>{rows}</table></section>"
    )


def _components_section(report: Mapping[str, Any], run_dir: Path) -> str:
    components = report.get("components", [])
    if not components:
        return ""
    rows = "".join(
        f"<tr><td><code>{_e(c.get('slot', '-'))}</code></td><td>{_e(c.get('plugin') or '-')}</td>"
        f"<td>{_e(component_status(c))}</td>{_value_cell(c.get('parameters', '-'))}"
        f"<td>{_e(c.get('checkpoint', '-'))}</td></tr>"
        for c in components
    )
    parts = [
        '<section id="components"><h2>Components</h2><table class="components"><tr><th>slot</th><th>plugin</th>'
        f"<th>status</th><th>parameters</th><th>checkpoint round trip</th></tr>{rows}</table>"
    ]
    renders = [c for c in components if "render" in c]
    if renders:
        parts.append('<h3>Sensors: a 2 mm ball pressed 0.2, 0.5 and 1.0 mm deep</h3><div class="row">')
        parts += [
            _figure(
                run_file(run_dir, report, c["render"]),
                f"{c['plugin']} ({c['slot']}): the three presses, shallowest first, left to right and top to bottom.",
                Path(c["render"]).name,
            )
            for c in renders
        ]
        parts.append("</div>")
    for c in components:
        if "data" in c:
            data = c["data"]
            shown = min(16, data.get("samples", 16))
            parts.append(
                f"<h3>Data: {_e(c['plugin'])} ({_e(c['slot'])})</h3>"
                f"<p>{_e(format_value(data.get('samples')))} samples, {_e(data.get('classes'))} classes. "
                f"Example text: &ldquo;{_e(data.get('example_text', ''))}&rdquo;</p>"
            )
            parts.append(
                _figure(
                    run_file(run_dir, report, data["preview"]),
                    f"The dataset's first {shown} samples, each as its tactile image followed by its "
                    "visual image (the tactile image again when the dataset has none), four pairs "
                    "per row.",
                    Path(data["preview"]).name,
                )
            )
    sanity = [c for c in components if "sanity" in c]
    if sanity:
        levels = list(dict.fromkeys(level for c in sanity for level in c["sanity"]))
        head = "".join(f"<th>{_e(level.replace('noise_sigma=', 'noise σ='))}</th>" for level in levels)
        body = "".join(
            f"<tr><td>{_e(c['plugin'])}</td>"
            + "".join(_value_cell(c["sanity"].get(level)) for level in levels)
            + "</tr>"
            for c in sanity
        )
        parts.append(
            "<h3>Metric sanity: a smooth synthetic 64&times;64 image against noisy copies of itself</h3>"
            f'<table class="sanity"><tr><th>metric</th>{head}</tr>{body}</table>'
        )
    parts.append("</section>")
    return "".join(parts)


def render_html(report: Mapping[str, Any], run_dir: str | Path) -> str:
    """The demo report of the run in ``run_dir`` (its report.json's content: ``report``) as one
    self-contained HTML page: a header (scene, date, wall time, peak memory), the stage table,
    each stage's scores, loss curve and pictures, what was skipped and why, and the components."""
    run_dir = Path(run_dir)
    stages = list(report.get("stages", []))
    skipped = skipped_items(report)
    losses = read_losses(run_dir)
    body = [_header(report, run_dir)]
    if stages:
        body.append(_stages_overview(stages))
    body += [_stage_section(entry, report, run_dir, losses, skipped) for entry in stages]
    body.append(_skipped_section(skipped))
    body.append(_components_section(report, run_dir))
    body.append(
        "<footer>Written by <code>vqtouch demo</code>; rebuild with <code>vqtouch report RUN_DIR</code>. "
        "The run folder also holds <code>report.json</code> (these numbers), <code>report.md</code>, "
        "<code>config.json</code> (the resolved config), <code>env.json</code> (versions) and "
        "<code>metrics.jsonl</code> (every logged step).</footer>"
    )
    title = f"vqtouch demo: {report.get('scene', '')}"
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        f"<title>{_e(title)}</title><style>{_STYLE}</style></head>\n<body><main>\n"
        + "\n".join(part for part in body if part)
        + "\n</main></body></html>\n"
    )

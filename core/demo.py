"""``vqtouch demo``: run a scene end to end with what is installed and write a report.

For each stage of the scene the demo builds the selected components, checks that each
survives a checkpoint round trip bit for bit, and runs the stage's work where a plugin
provides it.  Stages whose plugins are not installed are reported as such, never faked.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import torch
from torch import nn

from .checkpoint import load, save
from .assembly import build_context, enrich_context
from .components import Metric, SensorFamily, TactileDataset
from .config import SLOT_KINDS, ExperimentConfig
from .errors import VqtouchError
from .images import image_grid, save_png
from .progress import progress
from .runs import RunDir
from .seeding import make_generator, seed_everything


def _parameter_count(component: Any) -> int:
    return sum(p.numel() for p in component.parameters()) if isinstance(component, nn.Module) else 0


def _roundtrip(component: nn.Module, path: Any, host: Any) -> str:
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


def _ball_presses(image_size: int, field_of_view_mm: float, radius_mm: float = 2.0) -> torch.Tensor:
    """Height maps (mm) of a 2 mm ball pressed 0.2, 0.5 and 1.0 mm deep: a sensor-agnostic probe."""
    axis = (torch.arange(image_size) + 0.5) / image_size * field_of_view_mm - field_of_view_mm / 2
    ys, xs = torch.meshgrid(axis, axis, indexing="ij")
    ball = (radius_mm**2 - xs**2 - ys**2).clamp_min(0).sqrt()
    return torch.stack([(ball - (radius_mm - depth)).clamp_min(0) for depth in (0.2, 0.5, 1.0)])


def _preview_dataset(dataset: TactileDataset, run: RunDir, slot: str, count: int = 16) -> dict[str, Any]:
    """Save the first samples (tactile | visual) and measure how fast samples come."""
    count = min(count, len(dataset))
    start = time.perf_counter()
    samples = [dataset[index] for index in range(count)]
    seconds = time.perf_counter() - start
    images = [image for sample in samples for image in (sample["tactile"], sample.get("visual", sample["tactile"]))]
    path = save_png(image_grid(torch.stack(images), columns=8), run.path / f"preview_{slot.replace('.', '_')}.png")
    labels = [dataset.class_names[s["label"]] for s in samples if s["label"] >= 0 and dataset.class_names]
    return {"samples": len(dataset), "classes": dataset.num_classes, "samples_per_second": round(count / seconds, 1),
            "preview": str(path), "first_labels": labels[:8], "example_text": samples[0].get("text", "")}


#: How ``vqtouch demo`` scales a scene down to minutes on a laptop CPU (``--full`` skips it).
DEMO_SCALE = {"train.steps": 40, "train.checkpoint_every": 40, "train.log_every": 10, "data.batch_size": 8,
              "data.dataset.num_samples": 240, "tokenizer.encoder.channels": 32}


def scale_for_demo(config: ExperimentConfig, host: Any) -> ExperimentConfig:
    """``config`` with the DEMO_SCALE caps applied wherever the config has such a value."""
    from .config import validate_experiment

    data = config.to_dict()
    for path, cap in DEMO_SCALE.items():
        node = data
        *parents, last = path.split(".")
        for part in parents:
            node = node.get(part) if isinstance(node, dict) else None
        if isinstance(node, dict) and isinstance(node.get(last), int):
            node[last] = min(node[last], cap) if "every" not in last else cap
    return validate_experiment(data, host)


def run_demo(config: ExperimentConfig, host: Any, run: RunDir) -> dict[str, Any]:
    """Run the demo for ``config`` inside ``run``; returns the report (also written to disk)."""
    seed_everything(config.seed, config.deterministic)
    generator = make_generator(config.seed)
    report: dict[str, Any] = {"scene": config.scene, "run_dir": str(run.path), "stages": [], "components": []}
    missing = dict((path, stage) for stage, path in config.missing_slots())
    built: dict[str, Any] = {}
    context = build_context(config)
    # The data come first: their class count is part of the context the models are built with.
    ordered = sorted(config.required_slots(), key=lambda p: (p != "data.dataset", p != "tokenizer.encoder"))
    for path in progress(ordered, desc="components", unit="slot"):
        value = config.slot(path)
        if value is None and path not in missing:  # an optional slot left empty
            continue
        if path in missing:
            choices = host.registry(SLOT_KINDS[path]).names()
            reason = (f"no plugin selected; installed: {', '.join(choices)}" if choices
                      else f"no {SLOT_KINDS[path]} plugin installed yet")
            report["components"].append({"slot": path, "plugin": None, "status": f"missing: {reason}"})
            continue
        for index, item in enumerate(value if isinstance(value, list) else [value]):
            slot = f"{path}[{index}]" if isinstance(value, list) else path
            record: dict[str, Any] = {"slot": slot, "plugin": item.name}
            start = time.perf_counter()
            try:
                component = host.build(SLOT_KINDS[path], item, context)
            except VqtouchError as exc:
                record["status"] = f"skipped: {exc}"
                report["components"].append(record)
                continue
            record["build_seconds"] = round(time.perf_counter() - start, 3)
            record["parameters"] = _parameter_count(component)
            if isinstance(component, nn.Module):
                record["checkpoint"] = _roundtrip(component, run.checkpoints / f"{slot.replace('.', '_')}.safetensors", host)
            if isinstance(component, SensorFamily):
                with torch.no_grad():
                    presses = _ball_presses(config.data.image_size, component.field_of_view_mm)
                    images = component.render(presses, generator=generator)
                record["render"] = str(save_png(image_grid(images), run.path / f"render_{slot}.png"))
            if isinstance(component, Metric):
                record["sanity"] = _metric_sanity(component, generator)
            if isinstance(component, TactileDataset):
                record["data"] = _preview_dataset(component, run, slot)
            context = enrich_context(context, component)
            record["status"] = "built"
            built[slot] = component
            report["components"].append(record)
    for stage in config.stages:
        needs = [path for s, path in config.missing_slots() if s == stage]
        entry: dict[str, Any] = {"stage": stage}
        if needs:
            entry["status"] = f"waiting for: {', '.join(needs)}"
        else:
            start = time.perf_counter()
            try:
                result = host.pm.hook.vqtouch_run_stage(stage=stage, config=config, host=host, run=run)
            except VqtouchError as exc:
                result, entry["status"] = None, f"failed: {exc}"
            if result is not None:
                entry |= {"status": f"ran ({time.perf_counter() - start:.0f} s)", "result": result}
            entry.setdefault("status", "components ready (no plugin runs this stage yet)")
        report["stages"].append(entry)
    run.write_json("report.json", report)
    run.write_text("report.md", render_report(config, report))
    return report


def render_report(config: ExperimentConfig, report: dict[str, Any]) -> str:
    """The human-readable report.md."""
    lines = [f"# vqtouch demo: scene `{config.scene}`", "", config.description, "",
             "## Stages", "", "| stage | status |", "|---|---|"]
    lines += [f"| {s['stage']} | {s['status']} |" for s in report["stages"]]
    for s in report["stages"]:
        if "result" in s:
            result = s["result"]
            scores = ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                               for k, v in result.items() if k != "picture")
            lines += ["", f"### {s['stage']}", "", scores]
            if "picture" in result:
                lines += ["", f"![{s['stage']}]({result['picture']})"]
    lines += ["", "## Components", "", "| slot | plugin | status | parameters | checkpoint round trip |",
              "|---|---|---|---|---|"]
    for c in report["components"]:
        lines.append(f"| {c['slot']} | {c['plugin'] or '-'} | {c['status']} | {c.get('parameters', '-')} "
                     f"| {c.get('checkpoint', '-')} |")
    renders = [c for c in report["components"] if "render" in c]
    if renders:
        lines += ["", "## Sensors (a 2 mm ball pressed 0.2, 0.5 and 1.0 mm deep)", ""]
        lines += [f"- `{c['slot']}` ({c['plugin']}): ![{c['slot']}]({Path(c['render']).name})" for c in renders]
    for c in report["components"]:
        if "data" in c:
            data = c["data"]
            lines += ["", f"## Data (`{c['slot']}`: {c['plugin']})", "",
                      f"{data['samples']} samples, {data['classes']} classes, {data['samples_per_second']} samples/s "
                      f"on first access. Example text: \"{data['example_text']}\"", "",
                      f"![tactile | visual pairs]({Path(data['preview']).name})"]
    sanity = [c for c in report["components"] if "sanity" in c]
    if sanity:
        lines += ["", "## Metric sanity (synthetic 64x64 image vs noisy copies)", ""]
        for c in sanity:
            lines.append(f"- `{c['plugin']}`: {json.dumps(c['sanity'])}")
    lines += ["", f"Resolved config: `config.json`; environment: `env.json`; run: `{report['run_dir']}`", ""]
    return "\n".join(lines)

"""``vqtouch demo``: run a scene end to end with what is installed and write a report.

For each stage of the scene the demo builds the selected components, checks that each
survives a checkpoint round trip bit for bit, and runs the stage's work where a plugin
provides it.  Stages whose plugins are not installed are reported as such, never faked.
"""

from __future__ import annotations

import json
import time
from typing import Any

import torch
from torch import nn

from .checkpoint import load, save
from .components import Metric, SensorFamily
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


def _sphere_presses(image_size: int) -> torch.Tensor:
    """Height maps (mm) of three ball presses of growing depth: a sensor-agnostic probe."""
    ys, xs = torch.meshgrid(torch.linspace(-1, 1, image_size), torch.linspace(-1, 1, image_size), indexing="ij")
    radius_sq = xs**2 + ys**2
    return torch.stack([(depth - radius_sq * 2.0).clamp_min(0) for depth in (0.1, 0.3, 0.6)])


def run_demo(config: ExperimentConfig, host: Any, run: RunDir) -> dict[str, Any]:
    """Run the demo for ``config`` inside ``run``; returns the report (also written to disk)."""
    seed_everything(config.seed, config.deterministic)
    generator = make_generator(config.seed)
    report: dict[str, Any] = {"scene": config.scene, "run_dir": str(run.path), "stages": [], "components": []}
    missing = dict((path, stage) for stage, path in config.missing_slots())
    built: dict[str, Any] = {}
    for path in progress(config.required_slots(), desc="components", unit="slot"):
        value = config.slot(path)
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
                component = host.build(SLOT_KINDS[path], item)
            except VqtouchError as exc:
                record["status"] = f"skipped: {exc}"
                report["components"].append(record)
                continue
            record["build_seconds"] = round(time.perf_counter() - start, 3)
            record["parameters"] = _parameter_count(component)
            if isinstance(component, nn.Module):
                record["checkpoint"] = _roundtrip(component, run.checkpoints / f"{slot.replace('.', '_')}.safetensors", host)
            if isinstance(component, SensorFamily) and "render" in config.stages:
                with torch.no_grad():
                    images = component.render(_sphere_presses(config.data.image_size), generator=generator)
                record["render"] = str(save_png(image_grid(images), run.path / f"render_{slot}.png"))
            if isinstance(component, Metric):
                record["sanity"] = _metric_sanity(component, generator)
            record["status"] = "built"
            built[slot] = component
            report["components"].append(record)
    for stage in config.stages:
        needs = [path for s, path in config.missing_slots() if s == stage]
        status = "components ready" if not needs else f"waiting for: {', '.join(needs)}"
        report["stages"].append({"stage": stage, "status": status})
    run.write_json("report.json", report)
    run.write_text("report.md", render_report(config, report))
    return report


def render_report(config: ExperimentConfig, report: dict[str, Any]) -> str:
    """The human-readable report.md."""
    lines = [f"# vqtouch demo: scene `{config.scene}`", "", config.description, "",
             "## Stages", "", "| stage | status |", "|---|---|"]
    lines += [f"| {s['stage']} | {s['status']} |" for s in report["stages"]]
    lines += ["", "## Components", "", "| slot | plugin | status | parameters | checkpoint round trip |",
              "|---|---|---|---|---|"]
    for c in report["components"]:
        lines.append(f"| {c['slot']} | {c['plugin'] or '-'} | {c['status']} | {c.get('parameters', '-')} "
                     f"| {c.get('checkpoint', '-')} |")
    sanity = [c for c in report["components"] if "sanity" in c]
    if sanity:
        lines += ["", "## Metric sanity (synthetic 64x64 image vs noisy copies)", ""]
        for c in sanity:
            lines.append(f"- `{c['plugin']}`: {json.dumps(c['sanity'])}")
    lines += ["", f"Resolved config: `config.json`; environment: `env.json`; run: `{report['run_dir']}`", ""]
    return "\n".join(lines)

"""``vqtouch demo``: run a scene end to end with what is installed and write a report.

The demo runs each stage of the scene (scaled down unless ``--full``), then reports on
every component the stages need: its size, a bit-for-bit checkpoint round trip, and what
it does (a sensor's render, a metric's sanity scores, a dataset's preview).  A stage that
cannot run says why; nothing is faked.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch
from torch import nn

from .assembly import Assembly
from .checkpoint import load, save
from .components import Metric, SensorFamily, TactileDataset
from .config import ExperimentConfig, validate_experiment
from .errors import VqtouchError
from .image_size import ImageSize, image_hw, pixel_centres_mm
from .images import image_grid, save_png
from .progress import progress
from .runs import RunDir
from .seeding import make_generator
from .stages import empty_slot_reason, missing_slots, required_slots, run_stage


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
    return {"samples": len(dataset), "classes": dataset.num_classes, "preview": str(path), "first_labels": labels[:8], "example_text": samples[0].get("text", "")}


#: Caps on core's own options for ``vqtouch demo`` (plugins and stages declare their own caps
#: when they register: ``demo={...}``).
CORE_DEMO_CAPS = {"data.batch_size": 8}


def _capped(data: dict[str, Any], path: str, cap: Any) -> None:
    """Lower the number at ``path`` of the nested dict ``data`` to ``cap`` (other values are left alone)."""
    node: Any = data
    *parents, last = path.split(".")
    for part in parents:
        node = node.get(part) if isinstance(node, dict) else None
    if isinstance(node, dict) and isinstance(node.get(last), (int, float)) and not isinstance(node.get(last), bool):
        node[last] = min(node[last], cap)


def scale_for_demo(config: ExperimentConfig, host: Any) -> ExperimentConfig:
    """``config`` scaled down to minutes on a laptop CPU: core's caps, each stage's ``demo`` caps on
    its section and each selected plugin's ``demo`` caps on its options."""
    data = config.to_dict()
    for path, cap in CORE_DEMO_CAPS.items():
        _capped(data, path, cap)
    for name in config.stages:
        for path, cap in host.stage(name).demo.items():
            _capped(data, f"{name}.{path}", cap)
    for path, info in host.slots.items():
        value = config.slot(path)
        for index, item in (enumerate(value) if info.many else [(None, value)]):
            if item is None:
                continue
            prefix = path if index is None else f"{path}.{index}"
            for option, cap in host.registry(info.kind).get(item.name).demo.items():
                node = data
                for part in prefix.split("."):
                    node = node[int(part)] if isinstance(node, list) else node[part]
                _capped(node, option, cap)
    return validate_experiment(data, host)


def run_demo(config: ExperimentConfig, host: Any, run: RunDir) -> dict[str, Any]:
    """Run every stage of ``config`` in ``run``, then describe each component the stages need.

    Stages run through :func:`run_stage` with one shared :class:`Assembly`, so every component
    is built once.  Afterwards each required slot is reported: parameters, a bit-for-bit
    checkpoint round trip, a sensor's render of a ball press, a metric's sanity scores, a
    dataset's preview.  Returns the report (also written as report.json and report.md).
    """
    assembly = Assembly(config, host)
    report: dict[str, Any] = {"scene": config.scene, "run_dir": str(run.path), "stages": [], "components": []}
    for stage in progress(config.stages, desc="stages", unit="stage"):
        outcome = run_stage(stage, assembly, run)
        entry: dict[str, Any] = {"stage": stage, "status": outcome.describe()}
        if outcome.result is not None:
            entry["result"] = outcome.result
        report["stages"].append(entry)
    generator = make_generator(config.seed)
    for path in required_slots(config, host):
        info = host.slots[path]
        value = config.slot(path)
        if value is None or value == []:
            if path in dict((p, s) for s, p in missing_slots(config, host)):
                report["components"].append({"slot": path, "plugin": None,
                                              "status": f"missing: {empty_slot_reason(path, host)}"})
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
            record: dict[str, Any] = {"slot": slot, "plugin": item.name, "status": "built",
                                      "parameters": _parameter_count(component)}
            if isinstance(component, nn.Module):
                record["checkpoint"] = _roundtrip(component, run.checkpoints / f"{slot.replace('.', '_')}.safetensors",
                                                  host)
            if isinstance(component, SensorFamily):
                with torch.no_grad():
                    presses = _ball_presses(config.data.image_size, component)
                    images = component.render(presses, generator=generator)
                record["render"] = str(save_png(image_grid(images), run.path / f"render_{slot}.png"))
            if isinstance(component, Metric):
                record["sanity"] = _metric_sanity(component, generator)
            if isinstance(component, TactileDataset):
                record["data"] = _preview_dataset(component, run, slot)
            report["components"].append(record)
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
                      f"{data['samples']} samples, {data['classes']} classes. "
                      f"Example text: \"{data['example_text']}\"", "",
                      f"![tactile | visual pairs]({Path(data['preview']).name})"]
    sanity = [c for c in report["components"] if "sanity" in c]
    if sanity:
        lines += ["", "## Metric sanity (synthetic 64x64 image vs noisy copies)", ""]
        for c in sanity:
            lines.append(f"- `{c['plugin']}`: {json.dumps(c['sanity'])}")
    lines += ["", f"Resolved config: `config.json`; environment: `env.json`; run: `{report['run_dir']}`", ""]
    return "\n".join(lines)

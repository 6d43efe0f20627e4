"""A demo run folder for the report tests, made without running the demo: a report.json in the
layout ``run_demo`` writes, real PNGs made by vqtouch.plugins.utils.images, a metrics.jsonl, and every
form a skip is reported in.  The report test modules load it by file (test modules cannot import
each other under --import-mode=importlib)."""

from __future__ import annotations

import json
from pathlib import Path

import torch

#: The report was written in another folder: pictures recorded under it must be found in the copy.
RECORDED_RUN_DIR = "/elsewhere/runs/original"

#: Every reason the synthetic report gives for a skip, each in another of the forms it can take.
SKIP_REASONS = (
    "no weights file for fd_effnetlite0: set VQTOUCH_WEIGHTS_DIR",
    "the dataset has no labels",
    "no held-out samples (data.val_fraction=0)",
    "needs pretrained LPIPS heads",
)

#: The pictures (run-relative name: (width, height) in pixels) the synthetic report names.
PICTURES = {
    "reconstructions.png": (2 + 8 * 18, 2 + 2 * 18),
    "gen/samples.png": (2 + 4 * 34, 2 + 3 * 34),
    "render_sensor.png": (2 + 2 * 34, 2 + 2 * 34),
}


def _grid_png(path: Path, count: int, size: int, columns: int, seed: int) -> Path:
    from vqtouch.plugins.utils.images import image_grid, save_png

    images = torch.rand(count, 3, size, size, generator=torch.Generator().manual_seed(seed))
    return save_png(image_grid(images, columns=columns), path)


def synthetic_run(folder: Path) -> Path:
    """Write a demo run folder into ``folder`` (created): three stages (two ran, one cannot run; their
    scores beside the no-contact background's and a ceiling's), three components, pictures in the run
    and in a sub-folder, loss lines; returns ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    _grid_png(folder / "reconstructions.png", 16, 16, 8, seed=1)
    _grid_png(folder / "gen" / "samples.png", 12, 32, 4, seed=2)
    _grid_png(folder / "render_sensor.png", 3, 32, 2, seed=3)
    losses = [{"stage": "tokenizer", "step": step, "loss": 1.0 / step, "l1": 0.5} for step in (1, 2, 3, 4)]
    losses += [{"stage": "tokenizer", "step": 4, "val_loss": 0.2}, {"stage": "generator", "step": 1, "loss": 3.0}]
    (folder / "metrics.jsonl").write_text("".join(json.dumps(line) + "\n" for line in losses) + '{"cut sho')
    report = {
        "scene": "label-to-touch",
        "description": "Generate tactile images of a given object class.",
        "run_dir": RECORDED_RUN_DIR,
        "started": "2025-01-02T03:04:05+00:00",
        "seconds": 83.4,
        "peak_rss_mb": 1536.25,
        "stages": [
            {
                "stage": "tokenizer",
                "status": "ran (3 s)",
                "seconds": 3.21,
                "result": {
                    "steps": 40,
                    "psnr": 29.16341,
                    "ssim": 0.82712,
                    "codes_used": 1234567,
                    "background_psnr": 31.5984,
                    "background_ssim": 0.9254,
                    "contact_fraction": 0.2744,
                    "contact_psnr": 25.9237,
                    "background_contact_psnr": 25.2733,
                    "picture": "reconstructions.png",
                    "caption": "Held-out images (top) above their reconstructions.",
                    "skipped": {"fd_effnetlite0": SKIP_REASONS[0]},
                },
            },
            {
                "stage": "generator",
                "status": "ran (5 s)",
                "seconds": 5.0,
                "result": {
                    "psnr": 24.2953,
                    "ceiling_psnr": 29.3391,
                    "background_psnr": 32.5211,
                    "contact_mae": 0.05838,
                    "background_contact_mae": 0.04048,
                    "by_conditioner": {"0:label": 0.5},
                    "classifier_skipped": SKIP_REASONS[1],
                    "evaluation": f"skipped: {SKIP_REASONS[2]}",
                    "pictures": {"gen/samples.png": "Generated (top rows) above the ground truth."},
                },
            },
            {"stage": "reconstruct", "status": "cannot run: no trained tokenizer in this run", "seconds": 0.0},
        ],
        "components": [
            {
                "slot": "sensor",
                "plugin": "gelsight",
                "status": "built",
                "parameters": 0,
                "checkpoint": "ok (0.8 KiB)",
                "render": f"{RECORDED_RUN_DIR}/render_sensor.png",
            },
            {"slot": "tokenizer.discriminator", "plugin": "patchgan", "status": f"skipped: {SKIP_REASONS[3]}"},
            {
                "slot": "metrics[0]",
                "plugin": "psnr",
                "status": "built",
                "parameters": 0,
                "sanity": {"noise_sigma=0.0": 100.0, "noise_sigma=0.1": 20.4732},
            },
        ],
    }
    (folder / "report.json").write_text(json.dumps(report, indent=2))
    return folder

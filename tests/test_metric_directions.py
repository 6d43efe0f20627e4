"""A metric plugin declares which way is better (``Metric.higher_is_better``) and the report follows
it, with no edit to the built-in table (plugins/evaluation/directions.py, plugins/report/demo.py)."""

from __future__ import annotations

import json
from typing import Literal

import pytest

from vqtouch.core import Metric, PluginConfig, hookimpl, load_plugins
from vqtouch.plugins.runtime.run_dir import RunDir
from vqtouch.core.config import resolve_config
from vqtouch.plugins.evaluation.directions import declared_directions, direction_arrow, lower_is_better
from vqtouch.plugins.report.demo import run_demo


class RoughnessGapConfig(PluginConfig):
    """Options of the test's ``roughness_gap`` metric (none)."""

    name: Literal["roughness_gap"] = "roughness_gap"


class RoughnessGap(Metric):
    """Mean absolute difference of the images' local contrast: lower is better, and its name says nothing."""

    higher_is_better = False

    def __init__(self) -> None:
        self.reset()

    def update(self, predicted_B3HW, target_B3HW):
        gap = (predicted_B3HW.std(dim=(2, 3)) - target_B3HW.std(dim=(2, 3))).abs().mean(dim=1)
        self.total += float(gap.sum())
        self.count += len(gap)

    def compute(self):
        return self.total / max(self.count, 1)

    def reset(self):
        self.total, self.count = 0.0, 0


@hookimpl
def vqtouch_register_metrics(register):
    register(
        "roughness_gap",
        lambda config, context: RoughnessGap(),
        RoughnessGapConfig,
        description="Local-contrast gap (lower is better).",
    )


def test_declared_directions_decide_named_scores_and_only_inside_the_block():
    assert not lower_is_better("roughness_gap")  # unknown to the built-in table: higher-is-better
    with declared_directions({"roughness_gap": "lower"}):
        assert lower_is_better("roughness_gap") and lower_is_better("background_roughness_gap")
        assert direction_arrow("zero_shot_roughness_gap") == "↓"
        assert not lower_is_better("psnr") and lower_is_better("lpips")  # the others keep the table's
        with declared_directions({"lpips": "higher"}):  # a declared direction beats the table
            assert not lower_is_better("lpips") and lower_is_better("roughness_gap")
    assert not lower_is_better("roughness_gap") and lower_is_better("lpips")
    with pytest.raises(ValueError, match="must be 'higher' or 'lower'"):
        with declared_directions({"roughness_gap": "down"}):
            pass


def test_the_report_shows_a_plugin_metric_the_way_it_declares(tmp_path, make_plugin):
    host = load_plugins(autoload=False, extra=[make_plugin("roughness_metric", vqtouch_register_metrics)])
    overrides = [
        'stages=["tokenizer"]',
        "tokenizer.train.steps=1",
        "data.batch_size=4",
        "data.dataset.num_samples=12",
        "data.image_size=16",
        "tokenizer.loss.perceptual=none",
        "tokenizer.discriminator=null",
        'tokenizer.autoencoder={"name": "vqgan", "channels": 8, "norm_groups": 8, '
        '"channel_multipliers": [1, 2], "z_channels": 8, "embed_dim": 4, "mid_attention": false}',
        'metrics=[{"name": "psnr"}, {"name": "roughness_gap"}]',
    ]
    config = resolve_config("reconstruction", overrides=overrides, host=host)
    run = RunDir.create(config, host=host, path=tmp_path / "run")
    run_demo(config, host, run)
    recorded = json.loads((run.path / "report.json").read_text())
    assert recorded["directions"] == {"psnr": "higher", "roughness_gap": "lower"}
    html = (run.path / "report.html").read_text()
    row = html[html.index("<td>roughness_gap ") :]
    row = row[: row.index("</tr>")]
    assert 'title="lower is better">↓' in row
    markdown = (run.path / "report.md").read_text()
    assert "| roughness_gap ↓ |" in markdown

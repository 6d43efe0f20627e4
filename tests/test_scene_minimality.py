"""Model only what a scene requires: a run builds the slots its stages declare, and heavy
optional modules are imported only when a component that needs them is built.

Import checks run in a fresh interpreter, since sys.modules of the test process is shared.
"""

import subprocess
import sys

import pytest

from vqtouch.core import ConfigError, load_plugins, resolve_config
from vqtouch.plugins.runtime.execution import run_stage
from vqtouch.plugins.runtime.run_dir import RunDir
from vqtouch.core.assembly import Assembly
from vqtouch.plugins.report.demo import run_demo
from vqtouch.core.stages import required_slots

HEAVY = ("open_clip", "torchvision.models", "timm", "efficientnet_lite_pytorch")
HOST = load_plugins(autoload=False)


def _modules_after(code: str) -> set[str]:
    probe = code + "\nimport sys\nprint('HEAVY:' + ','.join(m for m in {heavy!r} if m in sys.modules))".format(
        heavy=HEAVY
    )
    result = subprocess.run(
        [sys.executable, "-c", probe],
        capture_output=True,
        text=True,
        timeout=300,
        env={"VQTOUCH_DISABLE_PLUGIN_AUTOLOAD": "1", "PATH": "/usr/bin:/bin"},
    )
    assert result.returncode == 0, result.stderr[-2000:]
    last = result.stdout.strip().splitlines()[-1]
    assert last.startswith("HEAVY:"), result.stdout
    return set(filter(None, last.removeprefix("HEAVY:").split(",")))


BUILD_SCENE = """
from vqtouch.core import Assembly, load_plugins, resolve_config, required_slots
host = load_plugins()
config = resolve_config({scene!r}, host=host)
assembly = Assembly(config, host)
built = {{}}
for path in required_slots(config, host):
    try:
        built[path] = assembly.component(path)
    except Exception as exc:
        built[path] = type(exc).__name__
"""


def test_importing_vqtouch_and_loading_plugins_imports_no_heavy_model_code():
    code = (
        "import vqtouch, vqtouch.core, vqtouch.plugins, vqtouch.conditioners, vqtouch.sensors\n"
        "host = vqtouch.core.load_plugins()\n"
        "import vqtouch.plugins.cli.app; vqtouch.plugins.cli.app.build_parser(host)"
    )
    assert _modules_after(code) == set()


def test_building_every_component_a_label_scene_needs_never_imports_open_clip():
    # Every slot the scene's stages declare is built (not a hand-picked list), including the label
    # conditioner: a plugin that imported open_clip at build time would fail this.
    code = BUILD_SCENE.format(scene="label-to-touch") + (
        "assert [type(c).__name__ for c in built['generator.conditioners']] == ['LabelConditioner'], built\n"
        "assert type(built['tokenizer.autoencoder']).__name__ == 'VqganAutoencoder', built"
    )
    assert _modules_after(code) == set()  # neither open_clip nor the EfficientNet of the visual conditioner


def test_building_the_vision_scene_imports_its_encoder_exactly_when_its_conditioner_is_built():
    resolve_only = (
        "from vqtouch.core import load_plugins, resolve_config\n"
        "host = load_plugins()\n"
        "config = resolve_config('vision-to-touch', host=host)\n"
        "assert config.generator.conditioners[0].name == 'visual'"
    )
    assert _modules_after(resolve_only) == set()
    # Building the scene's components imports the frozen EfficientNet, and nothing else heavy: this
    # also checks the probe itself can see a module being imported.
    code = BUILD_SCENE.format(scene="vision-to-touch") + (
        "assert type(built['generator.conditioners'][0]).__name__ == 'VisualConditioner', built"
    )
    assert _modules_after(code) == {"efficientnet_lite_pytorch"}
    # With the clip conditioner, open_clip (which then stops at its missing weights file).
    clip = BUILD_SCENE.format(scene="vision-to-touch").replace(
        "config = resolve_config('vision-to-touch', host=host)",
        "config = resolve_config('vision-to-touch', overrides=['generator.conditioners.0.name=clip'], host=host)",
    ) + ("assert built['generator.conditioners'] == 'MissingWeightsError', built")
    assert "open_clip" in _modules_after(clip) and "efficientnet_lite_pytorch" not in _modules_after(clip)


def test_required_slots_come_from_the_stages_declarations():
    config = resolve_config("reconstruction", overrides=['generator.conditioners=[{"name": "tactile"}]'], host=HOST)
    # The reconstruction scene has no generator stage: a conditioner set by mistake is not required.
    expected = []
    for stage in config.stages:
        expected += [p for p in HOST.stage(stage).slots if p not in expected]
    assert required_slots(config, HOST) == expected
    assert "generator.conditioners" not in expected and "tokenizer.autoencoder" in expected


TINY_RUN = [
    'stages=["tokenizer"]',
    "tokenizer.train.steps=1",
    "data.batch_size=4",
    "data.dataset.num_samples=12",
    "data.image_size=16",
    'tokenizer.autoencoder={"name": "vqgan", "channels": 8, "norm_groups": 8, "channel_multipliers": [1, 2], '
    '"z_channels": 8, "embed_dim": 4, "mid_attention": false}',
    "tokenizer.loss.perceptual=none",
    'generator.conditioners=[{"name": "tactile"}]',
]


def test_a_run_builds_exactly_the_slots_its_stages_need(tmp_path, built_kinds):
    config = resolve_config("reconstruction", overrides=TINY_RUN, host=HOST)
    run = RunDir.create(config, host=HOST, path=tmp_path / "run")
    report = run_demo(config, HOST, run)
    assert report["stages"][0]["status"].startswith("ran"), report["stages"]
    # Built during the stage and the report: the tokenizer stage's slots and the sensor that renders
    # the data and the no-contact background its scores stand next to; never the configured-but-unused
    # conditioner.
    assert "conditioner" not in built_kinds
    assert {"dataset", "sensor_family", "autoencoder", "quantizer", "metric"} <= set(built_kinds)
    assert "discriminator" not in built_kinds  # the scene names none
    assert {c["slot"] for c in report["components"]} == {
        "data.dataset",
        "tokenizer.autoencoder",
        "tokenizer.quantizer",
        "metrics[0]",
        "metrics[1]",
        "metrics[2]",
        "metrics[3]",
        "sensor",
    }


def test_each_component_is_built_once_per_run(tmp_path, built_kinds):
    """One assembly path: the demo's stages and its report share components instead of rebuilding."""
    config = resolve_config("reconstruction", overrides=TINY_RUN, host=HOST)
    run_demo(config, HOST, RunDir.create(config, host=HOST, path=tmp_path / "run"))
    counts = {kind: built_kinds.count(kind) for kind in set(built_kinds)}
    # The report's checkpoint round trips rebuild each nn.Module of a required slot once more by
    # loading it (the sensor is one: the tokenizer stage renders its no-contact background); the
    # dataset is never rebuilt, and the sensor not by the stage or the dataset.
    assert counts["dataset"] == 1 and counts["sensor_family"] == 2
    assert counts["autoencoder"] == 2 and counts["quantizer"] == 2


def test_a_stage_with_an_empty_needed_slot_says_which_and_the_choices(tmp_path):
    config = resolve_config("label-to-touch", overrides=["generator.model=null"], host=HOST)
    outcome = run_stage("generator", Assembly(config, HOST), RunDir.create(config, host=HOST, path=tmp_path / "r"))
    assert outcome.status == "unavailable"
    assert outcome.describe() == (
        "cannot run: needs generator.model, which the config leaves empty; choose with "
        "--set generator.model.name=<vq_diffusion>"
    )
    emptied = resolve_config("label-to-touch", overrides=["tokenizer.autoencoder=null"], host=HOST)
    outcome = run_stage("tokenizer", Assembly(emptied, HOST), RunDir.create(emptied, host=HOST, path=tmp_path / "e"))
    assert outcome.status == "unavailable"
    assert outcome.reason.startswith(
        "needs tokenizer.autoencoder, which the config leaves empty; choose with "
        "--set tokenizer.autoencoder.name=<dm_vqgan|mae|vqgan>"
    )


def test_an_empty_slot_asked_for_directly_names_the_choices():
    config = resolve_config("label-to-touch", overrides=["tokenizer.quantizer=null"], host=HOST)
    with pytest.raises(
        ConfigError,
        match=r"^this run needs tokenizer.quantizer, which the config leaves empty; "
        r"choose with --set tokenizer.quantizer.name=<ema_vq\|fsq\|identity\|vq>$",
    ):
        Assembly(config, HOST).component("tokenizer.quantizer")

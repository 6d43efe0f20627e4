"""The worked example of docs/extending.md: a third-party package adds a sensor family and a conditioner
through the `vqtouch` entry-point group; they become selectable by config and usable by the
CLI with no change to vqtouch itself."""

import json

from vqtouch.core import load_plugins

AUTOLOAD_ON = {"VQTOUCH_DISABLE_PLUGIN_AUTOLOAD": ""}


def test_plugins_lists_the_third_party_components(run_cli, example_plugin_site):
    result = run_cli("plugins", "--json", python_path=example_plugin_site, env_extra=AUTOLOAD_ON)
    assert result.returncode == 0, result.stderr
    rows = {(row["kind"], row["name"]): row for row in json.loads(result.stdout)}
    for key in (("sensor_family", "toy_sensor"), ("conditioner", "mean_colour")):
        assert rows[key]["package"] == "vqtouch-example-plugin" and rows[key]["version"] == "0.3.0"
        assert rows[key]["plugin"] == "example"


def test_autoload_off_hides_it_and_block_removes_it(run_cli, example_plugin_site):
    off = run_cli(
        "plugins", "--json", python_path=example_plugin_site, env_extra={"VQTOUCH_DISABLE_PLUGIN_AUTOLOAD": "1"}
    )
    blocked = run_cli(
        "plugins",
        "--json",
        python_path=example_plugin_site,
        env_extra={**AUTOLOAD_ON, "VQTOUCH_BLOCK_PLUGINS": "example"},
    )
    for result in (off, blocked):
        assert result.returncode == 0, result.stderr
        assert "toy_sensor" not in result.stdout and "label" in result.stdout


def test_selectable_by_config_with_options_validated(run_cli, example_plugin_site, tmp_path):
    config = tmp_path / "toy.toml"
    config.write_text('[sensor]\nname = "toy_sensor"\nnoise = 0.01\n[[generator.conditioners]]\nname = "mean_colour"\n')
    result = run_cli(
        "config",
        "show",
        "touch-to-touch",
        "--config",
        str(config),
        python_path=example_plugin_site,
        env_extra=AUTOLOAD_ON,
    )
    assert result.returncode == 0, result.stderr
    resolved = json.loads(result.stdout)
    assert resolved["sensor"] == {
        "name": "toy_sensor",
        "light_elevation_deg": 45.0,
        "tint": [0.9, 0.8, 0.7],
        "noise": 0.01,
    }
    assert resolved["generator"]["conditioners"] == [{"name": "mean_colour", "hidden": 32}]

    bad = run_cli(
        "config",
        "show",
        "touch-to-touch",
        "--config",
        str(config),
        "--set",
        "sensor.noise=5",
        python_path=example_plugin_site,
        env_extra=AUTOLOAD_ON,
    )
    assert bad.returncode == 2
    assert "sensor.noise: Input should be less than or equal to 0.2" in bad.stderr


def test_plugin_validation_hook_vetoes_bad_combination(run_cli, example_plugin_site):
    result = run_cli(
        "config",
        "show",
        "touch-to-touch",
        "--set",
        "generator.conditioners.0.name=mean_colour",
        "--set",
        "data.image_size=8",
        python_path=example_plugin_site,
        env_extra=AUTOLOAD_ON,
    )
    assert result.returncode == 2
    assert result.stderr.strip() == "vqtouch: error: conditioner 'mean_colour' needs data.image_size >= 16"


#: A tokenizer and a generator small enough to train in seconds inside a demo.
TINY_GENERATOR = [
    "--set",
    "data.image_size=32",
    "--set",
    "data.dataset.num_samples=16",
    "--set",
    "data.batch_size=4",
    "--set",
    "data.val_fraction=0.25",
    "--set",
    "tokenizer.train.steps=2",
    "--set",
    "tokenizer.loss.perceptual=none",
    "--set",
    "tokenizer.discriminator=null",
    "--set",
    "tokenizer.autoencoder.channels=16",
    "--set",
    "tokenizer.autoencoder.norm_groups=8",
    "--set",
    "tokenizer.autoencoder.channel_multipliers=[1,2]",
    "--set",
    "tokenizer.quantizer.codebook_size=32",
    "--set",
    "generator.model.depth=1",
    "--set",
    "generator.model.width=32",
    "--set",
    "generator.train.steps=2",
    "--set",
    "generator.num_samples=2",
    "--set",
    "generator.steps=2",
]


def test_demo_builds_and_checkpoints_the_plugin_components(run_cli, example_plugin_site, tmp_path):
    out = tmp_path / "run"
    result = run_cli(
        "demo",
        "--scene",
        "touch-to-touch",
        "--out",
        str(out),
        "--set",
        "generator.conditioners.0.name=mean_colour",
        "--set",
        "sensor.name=toy_sensor",
        "--set",
        'stages=["render", "tokenizer", "generator"]',
        "--set",
        "render.num_samples=4",
        *TINY_GENERATOR,
        python_path=example_plugin_site,
        env_extra=AUTOLOAD_ON,
    )
    assert result.returncode == 0, result.stderr
    report = json.loads((out / "report.json").read_text())
    by_slot = {c["slot"]: c for c in report["components"]}
    assert by_slot["sensor"]["plugin"] == "toy_sensor" and by_slot["sensor"]["checkpoint"].startswith("ok")
    conditioner = by_slot["generator.conditioners[0]"]
    assert conditioner["plugin"] == "mean_colour" and conditioner["checkpoint"].startswith("ok")
    assert (out / "render_sensor.png").is_file()
    stages = {s["stage"]: s["status"] for s in report["stages"]}
    # The render stage ran with the third-party sensor, and the generator trained and sampled with the
    # third-party conditioner: no edit to core or to the generator was needed for either.
    assert stages["render"].startswith("ran") and (out / "data" / "index.csv").read_text().count("toy_sensor") == 4
    assert stages["generator"].startswith("ran"), stages["generator"]
    generation = json.loads((out / "generation.json").read_text())
    assert generation["conditioner"] == "mean_colour" and generation["samples"] >= 1
    metadata = __import__("vqtouch.core", fromlist=["read_metadata"]).read_metadata(
        out / "checkpoints" / "sensor.safetensors"
    )
    assert metadata["example.calibration"] == "toy-v1"  # from the plugin's checkpoint-metadata hook
    env = json.loads((out / "env.json").read_text())
    assert env["plugins"]["example"] == {
        "module": "vqtouch_example_plugin",
        "package": "vqtouch-example-plugin",
        "version": "0.3.0",
    }


def test_plugin_adds_a_cli_command(run_cli, example_plugin_site):
    result = run_cli("example-render", "--radius", "0.5", python_path=example_plugin_site, env_extra=AUTOLOAD_ON)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("rendered (1, 3, 32, 32)")


def test_broken_third_party_plugin_names_itself_and_how_to_block(run_cli, example_plugin_site, tmp_path):
    broken = tmp_path / "broken_site"
    dist_info = broken / "vqtouch_broken-1.0.dist-info"
    dist_info.mkdir(parents=True)
    (dist_info / "METADATA").write_text("Metadata-Version: 2.1\nName: vqtouch-broken\nVersion: 1.0\n")
    (dist_info / "entry_points.txt").write_text("[vqtouch]\nbroken = vqtouch_broken_module\n")
    (broken / "vqtouch_broken_module.py").write_text("raise ImportError('needs libfoo')\n")
    result = run_cli("plugins", python_path=broken, env_extra=AUTOLOAD_ON)
    assert result.returncode == 2
    assert result.stderr.strip() == (
        "vqtouch: error: error loading plugin 'broken' from vqtouch-broken 1.0: "
        "ImportError: needs libfoo. Block it with VQTOUCH_BLOCK_PLUGINS=broken"
    )
    blocked = run_cli("plugins", python_path=broken, env_extra={**AUTOLOAD_ON, "VQTOUCH_BLOCK_PLUGINS": "broken"})
    assert blocked.returncode == 0


def test_a_third_party_stage_runs_in_a_scene_with_its_own_section(run_cli, example_plugin_site, tmp_path):
    out = tmp_path / "gallery"
    result = run_cli(
        "demo",
        "--scene",
        "reconstruction",
        "--out",
        str(out),
        "--set",
        'stages=["gallery"]',
        "--set",
        "gallery.depths_mm=[0.3, 0.9]",
        "--set",
        "sensor.name=toy_sensor",
        python_path=example_plugin_site,
        env_extra=AUTOLOAD_ON,
    )
    assert result.returncode == 0, result.stderr
    assert "1 of 1 stages ran" in result.stdout
    stage = json.loads((out / "report.json").read_text())["stages"][0]
    assert stage["stage"] == "gallery" and stage["status"].startswith("ran")
    shallow, deep = stage["result"]["mean_intensity"]
    assert shallow != deep  # the press depth shows in the toy sensor's shading
    assert (out / "gallery.png").is_file()
    listed = run_cli("config", "stages", python_path=example_plugin_site, env_extra=AUTOLOAD_ON)
    assert "gallery" in listed.stdout and "section: [gallery]; needs: sensor" in listed.stdout
    bad = run_cli(
        "config",
        "show",
        "reconstruction",
        "--set",
        "gallery.depths_mm=[]",
        python_path=example_plugin_site,
        env_extra=AUTOLOAD_ON,
    )
    assert bad.returncode == 2 and "gallery.depths_mm: List should have at least 1 item" in bad.stderr


def test_without_the_plugin_its_stage_is_unknown_and_listed_choices_exclude_it(run_cli, example_plugin_site):
    result = run_cli(
        "config",
        "show",
        "reconstruction",
        "--set",
        'stages=["gallery"]',
        python_path=example_plugin_site,
        env_extra={"VQTOUCH_DISABLE_PLUGIN_AUTOLOAD": "1"},
    )
    assert result.returncode == 2
    builtin = ", ".join(sorted(load_plugins(autoload=False).stages))  # the host without the example plugin
    assert result.stderr.strip().startswith(
        f"vqtouch: error: invalid configuration: stages: unknown stage 'gallery'; available: {builtin}"
    )


def test_a_run_made_with_an_uninstalled_plugin_names_its_distribution(run_cli, example_plugin_site, tmp_path):
    out = tmp_path / "made_with_plugin"
    made = run_cli(
        "demo",
        "--scene",
        "reconstruction",
        "--out",
        str(out),
        "--set",
        'stages=["gallery"]',
        "--set",
        "sensor.name=toy_sensor",
        python_path=example_plugin_site,
        env_extra=AUTOLOAD_ON,
    )
    assert made.returncode == 0, made.stderr
    # Reading the run back without the plugin: the error names the package to install, not a built-in.
    result = run_cli(
        "evaluate",
        "reconstruction",
        "--run",
        str(out),
        python_path=example_plugin_site,
        env_extra={"VQTOUCH_DISABLE_PLUGIN_AUTOLOAD": "1"},
    )
    assert result.returncode == 2
    assert result.stderr.strip() == (
        f"vqtouch: error: {out}: its config section 'gallery' belongs to stage "
        "'gallery' from vqtouch-example-plugin 0.3.0 (plugin 'example'), which is not "
        "installed here; pip install vqtouch-example-plugin"
    )


def test_a_checkpoint_made_by_an_uninstalled_plugin_names_its_distribution(run_cli, example_plugin_site, tmp_path):
    out = tmp_path / "ckpt"
    made = run_cli(
        "demo",
        "--scene",
        "touch-to-touch",
        "--out",
        str(out),
        "--set",
        "sensor.name=toy_sensor",
        "--set",
        'stages=["render"]',
        "--set",
        "render.num_samples=2",
        python_path=example_plugin_site,
        env_extra=AUTOLOAD_ON,
    )
    assert made.returncode == 0, made.stderr
    code = (
        "from vqtouch.core import load, load_plugins, CheckpointError\n"
        f"try:\n    load({str(out / 'checkpoints' / 'sensor.safetensors')!r}, host=load_plugins())\n"
        "except CheckpointError as exc:\n    print(exc)\n"
    )
    import subprocess
    import sys

    result = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=300,
        env={"VQTOUCH_DISABLE_PLUGIN_AUTOLOAD": "1", "PATH": "/usr/bin:/bin", "PYTHONPATH": str(example_plugin_site)},
    )
    assert result.stdout.strip().endswith(
        "made by sensor_family 'toy_sensor' from vqtouch-example-plugin 0.3.0, "
        "which is not installed here; pip install vqtouch-example-plugin"
    ), result

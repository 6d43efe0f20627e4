"""The README's worked example: a third-party package adds a sensor family and a conditioner
through the `vqtouch` entry-point group; they become selectable by config and usable by the
CLI with no change to vqtouch itself."""

import json

AUTOLOAD_ON = {"VQTOUCH_DISABLE_PLUGIN_AUTOLOAD": ""}


def test_plugins_lists_the_third_party_components(run_cli, example_plugin_site):
    result = run_cli("plugins", "--json", python_path=example_plugin_site, env_extra=AUTOLOAD_ON)
    assert result.returncode == 0, result.stderr
    rows = {(row["kind"], row["name"]): row for row in json.loads(result.stdout)}
    for key in (("sensor_family", "toy_sensor"), ("conditioner", "mean_colour")):
        assert rows[key]["package"] == "vqtouch-example-plugin" and rows[key]["version"] == "0.3.0"
        assert rows[key]["plugin"] == "example"


def test_autoload_off_hides_it_and_block_removes_it(run_cli, example_plugin_site):
    off = run_cli("plugins", "--json", python_path=example_plugin_site,
                  env_extra={"VQTOUCH_DISABLE_PLUGIN_AUTOLOAD": "1"})
    blocked = run_cli("plugins", "--json", python_path=example_plugin_site,
                      env_extra={**AUTOLOAD_ON, "VQTOUCH_BLOCK_PLUGINS": "example"})
    for result in (off, blocked):
        assert result.returncode == 0, result.stderr
        assert "toy_sensor" not in result.stdout and "label" in result.stdout


def test_selectable_by_config_with_options_validated(run_cli, example_plugin_site, tmp_path):
    config = tmp_path / "toy.toml"
    config.write_text('[sensor]\nname = "toy_sensor"\nnoise = 0.01\n[conditioner]\nname = "mean_colour"\n')
    result = run_cli("config", "show", "touch-to-touch", "--config", str(config), python_path=example_plugin_site,
                     env_extra=AUTOLOAD_ON)
    assert result.returncode == 0, result.stderr
    resolved = json.loads(result.stdout)
    assert resolved["sensor"] == {"name": "toy_sensor", "light_elevation_deg": 45.0, "tint": [0.9, 0.8, 0.7],
                                  "noise": 0.01}
    assert resolved["conditioner"] == {"name": "mean_colour", "hidden": 32}

    bad = run_cli("config", "show", "touch-to-touch", "--config", str(config), "--set", "sensor.noise=5",
                  python_path=example_plugin_site, env_extra=AUTOLOAD_ON)
    assert bad.returncode == 2
    assert "sensor.noise: Input should be less than or equal to 0.2" in bad.stderr


def test_plugin_validation_hook_vetoes_bad_combination(run_cli, example_plugin_site):
    result = run_cli("config", "show", "touch-to-touch", "--set", "conditioner.name=mean_colour",
                     "--set", "data.image_size=8", python_path=example_plugin_site, env_extra=AUTOLOAD_ON)
    assert result.returncode == 2
    assert result.stderr.strip() == "vqtouch: error: conditioner 'mean_colour' needs data.image_size >= 16"


def test_demo_builds_and_checkpoints_the_plugin_components(run_cli, example_plugin_site, tmp_path):
    out = tmp_path / "run"
    result = run_cli("demo", "--scene", "touch-to-touch", "--out", str(out), "--set", "conditioner.name=mean_colour",
                     "--set", "sensor.name=toy_sensor", "--set", 'stages=["render", "generator", "evaluate"]',
                     python_path=example_plugin_site, env_extra=AUTOLOAD_ON)
    assert result.returncode == 0, result.stderr
    report = json.loads((out / "report.json").read_text())
    by_slot = {c["slot"]: c for c in report["components"]}
    assert by_slot["sensor"]["plugin"] == "toy_sensor" and by_slot["sensor"]["checkpoint"].startswith("ok")
    assert by_slot["conditioner"]["plugin"] == "mean_colour" and by_slot["conditioner"]["checkpoint"].startswith("ok")
    assert (out / "render_sensor.png").is_file()
    metadata = __import__("vqtouch.core", fromlist=["read_metadata"]).read_metadata(
        out / "checkpoints" / "sensor.safetensors")
    assert metadata["example.calibration"] == "toy-v1"  # from the plugin's checkpoint-metadata hook
    env = json.loads((out / "env.json").read_text())
    assert env["plugins"]["example"] == {"module": "vqtouch_example_plugin", "package": "vqtouch-example-plugin",
                                         "version": "0.3.0"}


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
    assert result.stderr.strip() == ("vqtouch: error: error loading plugin 'broken' from vqtouch-broken 1.0: "
                                     "ImportError: needs libfoo. Block it with VQTOUCH_BLOCK_PLUGINS=broken")
    blocked = run_cli("plugins", python_path=broken, env_extra={**AUTOLOAD_ON, "VQTOUCH_BLOCK_PLUGINS": "broken"})
    assert blocked.returncode == 0

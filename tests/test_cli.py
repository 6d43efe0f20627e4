import json

import pytest

from vqtouch.core.cli import main


def test_plugins_lists_kind_package_version(capsys):
    assert main(["plugins"]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0].split()[:5] == ["KIND", "NAME", "PLUGIN", "PACKAGE", "VERSION"]
    assert any(line.split()[:4] == ["conditioner", "label", "label", "vqtouch"] for line in out.splitlines())


def test_plugins_json_and_kind_filter(capsys):
    assert main(["plugins", "--json", "--kind", "metric"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert {row["name"] for row in rows} == {"fd_effnetlite0", "psnr", "ssim"}
    assert all(row["package"] == "vqtouch" and row["version"] for row in rows)


def test_config_show_prints_resolved_json_and_notes_empty_slots(capsys):
    assert main(["config", "show", "label-to-touch", "--set", "seed=5"]) == 0
    captured = capsys.readouterr()
    config = json.loads(captured.out)
    assert config["seed"] == 5 and config["conditioner"]["name"] == "label"
    assert "note: generator is empty" in captured.err


def test_config_show_output_feeds_back_as_config_file(capsys, tmp_path):
    assert main(["config", "show", "touch-to-touch", "--set", "conditioner.width=24"]) == 0
    path = tmp_path / "resolved.json"
    path.write_text(capsys.readouterr().out)
    assert main(["config", "validate", str(path)]) == 0
    assert capsys.readouterr().out.startswith("ok: touch-to-touch")


def test_config_scenes_lists_paper_scenarios(capsys):
    assert main(["config", "scenes"]) == 0
    names = {line.split()[0] for line in capsys.readouterr().out.splitlines()}
    assert {"few-shot", "zero-shot", "cross-sensor", "vision-to-touch", "label-to-touch", "touch-to-touch"} <= names


def test_config_show_takes_the_scene_as_argument_or_option(capsys):
    assert main(["config", "show", "few-shot"]) == 0
    positional = capsys.readouterr().out
    assert main(["config", "show", "--scene", "few-shot"]) == 0
    assert capsys.readouterr().out == positional and '"scene": "few-shot"' in positional


@pytest.mark.parametrize("argv, message", [
    (["config", "show", "lable-to-touch"], "unknown scene 'lable-to-touch'; available: "),
    (["config", "show", "label-to-touch", "--set", "conditioner.name=clipp"], "did you mean 'clip'?"),
    (["config", "show", "label-to-touch", "--set", "train.steps=-1"], "train.steps: Input should be greater than"),
    (["config", "show", "label-to-touch", "--set", "oops"], "bad override 'oops'"),
    (["config", "validate", "/nonexistent.toml"], "config file '/nonexistent.toml' does not exist"),
    (["config", "show"], "name a scene, e.g. `vqtouch config show reconstruction`"),
    (["config", "show", "few-shot", "--scene", "zero-shot"], "two different scenes given: 'few-shot' and --scene"),
])
def test_user_errors_are_one_line_with_exit_2(capsys, argv, message):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("vqtouch: error: ") and message in err
    assert err.count("\n") == 1


def test_broken_checkpoint_via_demo_free_api_is_one_line(tmp_path, capsys):
    from vqtouch.core import CheckpointError, load

    path = tmp_path / "broken.safetensors"
    path.write_bytes(b"\x00" * 3)
    with pytest.raises(CheckpointError) as info:
        load(path)
    assert "\n" not in str(info.value)


def test_help_everywhere(capsys):
    for argv in (["--help"], ["plugins", "--help"], ["config", "show", "--help"], ["demo", "--help"]):
        with pytest.raises(SystemExit) as info:
            main(argv)
        assert info.value.code == 0
    assert "--set PATH=VALUE" in capsys.readouterr().out


def test_no_command_prints_help_and_fails(capsys):
    assert main([]) == 2
    assert "usage: vqtouch" in capsys.readouterr().out


TINY_DEMO = ["--set", "train.steps=2", "--set", "data.dataset.num_samples=12", "--set", "data.image_size=32",
             "--set", "tokenizer.loss.perceptual=none", "--set", "tokenizer.encoder.channels=16",
             "--set", "tokenizer.encoder.norm_groups=8", "--set", "tokenizer.encoder.channel_multipliers=[1,2]",
             "--set", "tokenizer.quantizer.codebook_size=32"]


def test_demo_writes_run_directory(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["--no-progress", "demo", "--scene", "label-to-touch", "--out", str(out),
                 "--set", "conditioner.num_classes=3", *TINY_DEMO]) == 0
    for name in ("config.json", "env.json", "report.md", "report.json", "checkpoints/conditioner.safetensors"):
        assert (out / name).is_file(), name
    env = json.loads((out / "env.json").read_text())
    assert env["seed"] == 0 and env["versions"]["torch"] and "label" in env["plugins"]
    assert env["argv"][:2] == ["vqtouch", "--no-progress"]
    report = json.loads((out / "report.json").read_text())
    by_slot = {c["slot"]: c for c in report["components"]}
    assert by_slot["conditioner"]["checkpoint"].startswith("ok")
    assert by_slot["generator"]["status"].startswith("missing")
    assert by_slot["metrics[0]"]["sanity"]["noise_sigma=0.0"] == 100.0
    stages = {s["stage"]: s for s in report["stages"]}
    assert stages["generator"]["status"] == "waiting for: generator"
    assert stages["tokenizer"]["status"].startswith("ran") and stages["tokenizer"]["result"]["steps"] == 2


def test_demo_runs_the_reconstruction_scene_through_the_stage_hook(tmp_path):
    """The tokenizer plugin answers vqtouch_run_stage for 'tokenizer' and 'reconstruct'."""
    out = tmp_path / "run"
    assert main(["--no-progress", "demo", "--out", str(out), *TINY_DEMO]) == 0  # default scene: reconstruction
    stages = {s["stage"]: s for s in json.loads((out / "report.json").read_text())["stages"]}
    assert stages["reconstruct"]["result"]["source"] == "48 real gelsight frames (taxim)"
    assert 0 < stages["reconstruct"]["result"]["ssim"] <= 1
    assert (out / "real_frames.png").is_file() and (out / "reconstructions.png").is_file()
    assert "![reconstruct](real_frames.png)" in (out / "report.md").read_text()


def test_demo_scales_the_scene_down_unless_full():
    from vqtouch.core import load_plugins, resolve_config
    from vqtouch.core.demo import scale_for_demo

    host = load_plugins(autoload=False)
    config = resolve_config("reconstruction", overrides=["train.steps=5000"], host=host)
    scaled = scale_for_demo(config, host)
    assert (scaled.train.steps, scaled.data.batch_size, scaled.data.dataset.num_samples) == (40, 8, 240)
    assert scaled.tokenizer.encoder.channels == 32 and config.tokenizer.encoder.channels == 64

import json
import subprocess
import sys
from typing import Literal

import pytest
from pydantic import Field

from vqtouch.core import ConfigError, PluginConfig, Section, hookimpl, load_plugins, resolve_config
from vqtouch.plugins.cli.app import build_parser, main
from vqtouch.core.config import scale_for_demo

#: The installed stages, as an unknown stage's message lists them.
STAGES = ", ".join(sorted(load_plugins(autoload=False).stages))


def test_plugins_lists_kind_package_version(capsys):
    assert main(["plugins"]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0].split()[:5] == ["KIND", "NAME", "PLUGIN", "PACKAGE", "VERSION"]
    assert any(line.split()[:4] == ["conditioner", "label", "label", "vqtouch"] for line in out.splitlines())
    assert any(line.split()[:4] == ["autoencoder", "dm_vqgan", "vqgan", "vqtouch"] for line in out.splitlines())
    assert any(line.split()[:4] == ["stage", "tokenizer", "tokenizer-stages", "vqtouch"] for line in out.splitlines())


def test_plugins_json_and_kind_filter(capsys):
    assert main(["plugins", "--json", "--kind", "metric"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert {row["name"] for row in rows} == {
        "fd_effnetlite0",
        "psnr",
        "ssim",
        "ms_ssim",
        "lpips",
        "fid",
        "kid",
        "kid_effnetlite0",
        "clip_score",
    }
    assert all(row["package"] == "vqtouch" and row["version"] for row in rows)
    assert main(["plugins", "--json", "--kind", "stage"]) == 0
    assert {row["name"] for row in json.loads(capsys.readouterr().out)} == {
        "render",
        "tokenizer",
        "reconstruct",
        "cluster",
        "adapt",
        "generator",
        "fewshot",
        "pretrained",
    }


def test_config_show_prints_resolved_json_and_notes_empty_slots(capsys):
    assert main(["config", "show", "label-to-touch", "--set", "seed=5"]) == 0
    captured = capsys.readouterr()
    config = json.loads(captured.out)
    assert config["seed"] == 5 and config["generator"]["conditioners"][0]["name"] == "label"
    assert captured.err == ""  # every slot the scene's stages need is filled
    assert main(["config", "show", "label-to-touch", "--set", "generator.model=null"]) == 0
    assert capsys.readouterr().err == (
        "note: stage(s) generator cannot run yet: needs generator.model, which the "
        "config leaves empty; choose with --set generator.model.name=<vq_diffusion>\n"
    )


def test_config_show_output_feeds_back_as_config_file(capsys, tmp_path):
    assert main(["config", "show", "touch-to-touch", "--set", "generator.conditioners.0.width=24"]) == 0
    path = tmp_path / "resolved.json"
    path.write_text(capsys.readouterr().out)
    assert json.loads(path.read_text())["generator"]["conditioners"][0]["width"] == 24
    assert main(["config", "validate", str(path)]) == 0
    assert capsys.readouterr().out.startswith("ok: touch-to-touch (stages: tokenizer, generator)")


def test_config_scenes_lists_paper_scenarios(capsys):
    assert main(["config", "scenes"]) == 0
    names = {line.split()[0] for line in capsys.readouterr().out.splitlines()}
    assert {"few-shot", "zero-shot", "cross-sensor", "vision-to-touch", "label-to-touch", "touch-to-touch"} <= names


def test_config_stages_lists_each_stage_with_its_section_and_slots(capsys, host):
    assert main(["config", "stages"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2 * len(host.stages)
    listed = {}
    for head, detail in zip(lines[::2], lines[1::2]):
        name = head.split()[0]
        listed[name] = detail.strip()
        assert head[len(name) :].strip() == host.stage(name).description
    assert sorted(listed) == sorted(host.stages)
    for name, detail in listed.items():
        stage = host.stage(name)
        fields = dict(part.split(": ", 1) for part in detail.split("; from ")[0].split("; "))
        assert fields["section"] == (f"[{name}]" if stage.section else "-")
        assert fields["needs"].split(", ") == list(stage.needs)
        optional = [path for path in stage.uses if path not in stage.needs]
        assert fields["uses"] == (", ".join(optional) or "-")
        assert detail.endswith(f"from {stage.source.describe()}")
    assert listed["tokenizer"].startswith(
        "section: [tokenizer]; needs: data.dataset, tokenizer.autoencoder, "
        "tokenizer.quantizer; uses: tokenizer.discriminator, metrics, sensor; "
        "from plugin 'tokenizer-stages'"
    )
    assert listed["reconstruct"].startswith(
        "section: -; needs: sensor, tokenizer.autoencoder, tokenizer.quantizer; uses: metrics;"
    )
    assert "needs: data.dataset; uses: sensor;" in listed["render"]
    assert "generator.model, generator.conditioners;" in listed["generator"]
    assert "cluster.clusterer" in listed["cluster"] and "target_sensor" in listed["adapt"]


def test_config_show_takes_the_scene_as_argument_or_option(capsys):
    assert main(["config", "show", "few-shot"]) == 0
    positional = capsys.readouterr().out
    assert main(["config", "show", "--scene", "few-shot"]) == 0
    assert capsys.readouterr().out == positional and '"scene": "few-shot"' in positional


@pytest.mark.parametrize(
    "argv, message",
    [
        (["config", "show", "lable-to-touch"], "unknown scene 'lable-to-touch'; available: "),
        (["config", "show", "label-to-touch", "--set", "generator.conditioners.0.name=clipp"], "did you mean 'clip'?"),
        (
            ["config", "show", "label-to-touch", "--set", "tokenizer.train.steps=-1"],
            "tokenizer.train.steps: Input should be greater than or equal to 0 (got -1)",
        ),
        (
            ["config", "show", "label-to-touch", "--set", "train.steps=3"],
            "config key 'train' (vqtouch 0.1.0) was split into tokenizer.train and generator.train",
        ),
        (
            ["config", "show", "label-to-touch", "--set", 'stages=["evaluate"]'],
            "stage 'evaluate' (vqtouch 0.1.0) was removed in 0.2.0",
        ),
        (
            ["config", "show", "label-to-touch", "--set", 'stages=["evaluat"]'],
            f"stages: unknown stage 'evaluat'; available: {STAGES}",
        ),
        (["config", "show", "label-to-touch", "--set", "oops"], "bad override 'oops'"),
        (["config", "validate", "/nonexistent.toml"], "config file '/nonexistent.toml' does not exist"),
        (["config", "show"], "name a scene, e.g. `vqtouch config show reconstruction`"),
        (["config", "show", "few-shot", "--scene", "zero-shot"], "two different scenes given: 'few-shot' and --scene"),
    ],
)
def test_user_errors_are_one_line_with_exit_2(capsys, argv, message):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("vqtouch: error: ") and message in err
    assert err.count("\n") == 1


def test_broken_checkpoint_via_demo_free_api_is_one_line(tmp_path, host):
    from vqtouch.core import CheckpointError, load

    path = tmp_path / "broken.safetensors"
    path.write_bytes(b"\x00" * 3)
    with pytest.raises(CheckpointError) as info:
        load(path, host=host)
    assert "\n" not in str(info.value)
    with pytest.raises(TypeError, match="host"):
        load(path)  # no hidden host: the caller says whose plugins rebuild the component


def test_help_everywhere(capsys):
    for argv in (
        ["--help"],
        ["plugins", "--help"],
        ["config", "show", "--help"],
        ["config", "stages", "--help"],
        ["demo", "--help"],
    ):
        assert main(argv) == 0
    assert "--set PATH=VALUE" in capsys.readouterr().out


def test_no_command_prints_help_and_fails(capsys):
    assert main([]) == 2
    assert "usage: vqtouch" in capsys.readouterr().out


def test_handlers_get_the_parsers_host(host):
    args = build_parser(host).parse_args(["config", "stages"])
    assert args.host is host
    with pytest.raises(TypeError):
        build_parser()


TINY_DEMO = [
    "--set",
    "tokenizer.train.steps=2",
    "--set",
    "data.dataset.num_samples=12",
    "--set",
    "data.image_size=32",
    "--set",
    "tokenizer.loss.perceptual=none",
    "--set",
    "tokenizer.autoencoder.channels=16",
    "--set",
    "tokenizer.autoencoder.norm_groups=8",
    "--set",
    "tokenizer.autoencoder.channel_multipliers=[1,2]",
    "--set",
    "tokenizer.quantizer.codebook_size=32",
]


def test_demo_writes_run_directory(tmp_path, capsys):
    out = tmp_path / "run"
    assert (
        main(
            [
                "--no-progress",
                "demo",
                "--scene",
                "label-to-touch",
                "--out",
                str(out),
                *TINY_DEMO,
                "--set",
                "generator.model.depth=1",
                "--set",
                "generator.model.width=16",
                "--set",
                "generator.model.heads=2",
                "--set",
                "generator.train.steps=2",
                "--set",
                "generator.num_samples=2",
                "--set",
                "generator.steps=2",
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert "scene label-to-touch: 2 of 2 stages ran, 0 cannot run, 0 failed (reasons in the report)" in printed
    for name in (
        "config.json",
        "env.json",
        "report.md",
        "report.json",
        "samples.png",
        "generation.json",
        "checkpoints/generator_conditioners[0].safetensors",
    ):
        assert (out / name).is_file(), name
    assert not (out / "checkpoints" / "latest").exists()  # the trainer no longer writes a `latest` file
    env = json.loads((out / "env.json").read_text())
    assert env["seed"] == 0 and env["versions"]["torch"] and "label" in env["plugins"]
    assert env["argv"][:2] == ["vqtouch", "--no-progress"]
    assert env["components"]["generator.conditioners.0"] == {
        "kind": "conditioner",
        "name": "label",
        "plugin": "label",
        "package": "vqtouch",
        "version": env["plugins"]["label"]["version"],
    }
    assert env["components"]["tokenizer.autoencoder"]["kind"] == "autoencoder"
    assert env["components"]["sensor"]["name"] == "gelsight"
    report = json.loads((out / "report.json").read_text())
    by_slot = {c["slot"]: c for c in report["components"]}
    assert by_slot["generator.conditioners[0]"]["checkpoint"].startswith("ok")
    assert by_slot["generator.model"]["checkpoint"].startswith("ok")
    assert by_slot["metrics[0]"]["sanity"]["noise_sigma=0.0"] == 100.0
    stages = {s["stage"]: s for s in report["stages"]}
    assert (
        stages["generator"]["status"].startswith("ran (") and stages["generator"]["result"]["samples"] == 1
    )  # 1 held out
    assert stages["tokenizer"]["status"].startswith("ran (") and stages["tokenizer"]["result"]["steps"] == 2
    assert "evaluate" not in stages


def test_demo_runs_the_reconstruction_scene_through_the_registered_stages(tmp_path, capsys):
    """The tokenizer-stages plugin registers 'tokenizer' and 'reconstruct'; the demo runs both via run_stage."""
    out = tmp_path / "run"
    assert main(["--no-progress", "demo", "--scene", "reconstruction", "--out", str(out), *TINY_DEMO]) == 0
    assert "scene reconstruction: 2 of 2 stages ran, 0 cannot run, 0 failed" in capsys.readouterr().out
    stages = {s["stage"]: s for s in json.loads((out / "report.json").read_text())["stages"]}
    assert list(stages) == ["tokenizer", "reconstruct"]
    assert stages["reconstruct"]["status"].startswith("ran (")
    assert stages["reconstruct"]["result"]["source"] == "48 real gelsight frames"
    assert 0 < stages["reconstruct"]["result"]["ssim"] <= 1
    assert (out / "real_frames.png").is_file() and (out / "reconstructions.png").is_file()
    assert "![reconstruct](real_frames.png)" in (out / "report.md").read_text()


def test_demo_scales_the_scene_down_unless_full(host):
    config = resolve_config("reconstruction", overrides=["tokenizer.train.steps=5000"], host=host)
    scaled = scale_for_demo(config, host)
    assert (scaled.tokenizer.train.steps, scaled.data.batch_size, scaled.data.dataset.num_samples) == (40, 8, 240)
    assert (scaled.tokenizer.train.checkpoint_every, scaled.tokenizer.train.log_every) == (40, 10)
    assert scaled.tokenizer.autoencoder.channels == 32 and config.tokenizer.autoencoder.channels == 64
    assert config.tokenizer.train.steps == 5000  # the input config is untouched
    # Caps only lower values: an option already below its cap is kept.
    small = resolve_config("reconstruction", overrides=["tokenizer.train.steps=3"], host=host)
    assert scale_for_demo(small, host).tokenizer.train.steps == 3


def test_demo_caps_come_from_the_registrations(host, make_plugin):
    # The built-in caps are the ones the plugins declared when they registered.
    config = resolve_config("reconstruction", overrides=["tokenizer.train.steps=5000"], host=host)
    scaled = scale_for_demo(config, host)
    tokenizer_caps = host.stage("tokenizer").demo
    assert tokenizer_caps == {"train.steps": 40, "train.checkpoint_every": 40, "train.log_every": 10}
    assert scaled.tokenizer.train.steps == tokenizer_caps["train.steps"]
    assert scaled.tokenizer.autoencoder.channels == host.registry("autoencoder").get("dm_vqgan").demo["channels"]
    assert scaled.data.dataset.num_samples == host.registry("dataset").get("procedural").demo["num_samples"]
    # A stage's caps apply only when the stage is listed: reconstruction does not render.
    assert scaled.render.num_samples == config.render.num_samples == 64
    rendering = resolve_config("reconstruction", overrides=['stages=["render"]'], host=host)
    assert scale_for_demo(rendering, host).render.num_samples == host.stage("render").demo["num_samples"] == 32

    # A third-party stage and component declare their own caps the same way.
    class ProbeSection(Section):
        width: int = Field(100, ge=1)

    class ProbeMetricConfig(PluginConfig):
        name: Literal["probe_metric"] = "probe_metric"
        window: int = Field(99, ge=1)

    @hookimpl
    def vqtouch_register_stages(register):
        register("probe", lambda job: {}, section=ProbeSection, demo={"width": 3})

    @hookimpl
    def vqtouch_register_metrics(register):
        register("probe_metric", lambda config, context: None, ProbeMetricConfig, demo={"window": 5})

    extended = load_plugins(
        autoload=False, extra=[make_plugin("probe_plugin", vqtouch_register_stages, vqtouch_register_metrics)]
    )
    probe = resolve_config(None, overrides=['stages=["probe"]', 'metrics=["psnr", "probe_metric"]'], host=extended)
    scaled = scale_for_demo(probe, extended)
    assert (probe.probe.width, probe.metrics[1].window) == (100, 99)
    assert (scaled.probe.width, scaled.metrics[1].window) == (3, 5)


DEMO_SIZE_PROBE = [
    'stages=["tokenizer"]',
    "tokenizer.quantizer=null",
    "tokenizer.discriminator=null",
    "tokenizer.train.steps=500",
    "tokenizer.train.checkpoint_every=500",
    "tokenizer.train.log_every=50",
    "data.image_size=16",
    "tokenizer.autoencoder.channels=48",
    "tokenizer.autoencoder.norm_groups=8",
    "tokenizer.autoencoder.channel_multipliers=[1,2]",
    "tokenizer.autoencoder.z_channels=8",
    "tokenizer.autoencoder.embed_dim=4",
]


@pytest.mark.parametrize("full", [True, False])
def test_demo_full_keeps_the_configured_size_and_scaled_uses_the_caps(tmp_path, capsys, full):
    # The tokenizer stage cannot run here (no quantizer), so only the resolved sizes are compared.
    out = tmp_path / "run"
    argv = ["--no-progress", "demo", "--scene", "reconstruction", "--out", str(out), *(["--full"] if full else [])]
    for override in DEMO_SIZE_PROBE:
        argv += ["--set", override]
    assert main(argv) == 0
    assert "scene reconstruction: 0 of 1 stages ran, 1 cannot run, 0 failed" in capsys.readouterr().out
    config = json.loads((out / "config.json").read_text())
    train = config["tokenizer"]["train"]
    sizes = (
        train["steps"],
        train["checkpoint_every"],
        train["log_every"],
        config["data"]["batch_size"],
        config["data"]["dataset"]["num_samples"],
        config["tokenizer"]["autoencoder"]["channels"],
    )
    assert sizes == ((500, 500, 50, 16, 1000, 48) if full else (40, 40, 10, 8, 240, 32))
    (stage,) = json.loads((out / "report.json").read_text())["stages"]
    assert stage["status"].startswith("cannot run: needs tokenizer.quantizer, which the config leaves empty")


def test_closed_stdout_pipe_exits_quietly():
    """`vqtouch plugins | head`: the reader goes away; no traceback, the usual SIGPIPE status."""
    process = subprocess.Popen(
        [sys.executable, "-m", "vqtouch.plugins.cli", "plugins"], stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    process.stdout.close()  # before the command has imported anything, let alone printed
    err = process.stderr.read().decode()
    assert process.wait(timeout=300) == 141
    assert err == ""


def test_broken_pipe_in_a_handler_is_quiet_in_process(capsys, monkeypatch):
    from vqtouch.plugins.cli import app as cli

    def closed_pipe(args):
        raise BrokenPipeError(32, "Broken pipe")

    monkeypatch.setattr(cli, "_cmd_plugins", closed_pipe)
    assert main(["plugins"]) == 141
    assert capsys.readouterr().err == ""


def test_ctrl_c_prints_interrupted(capsys, monkeypatch):
    from vqtouch.plugins.cli import app as cli

    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "_cmd_plugins", interrupted)
    assert main(["plugins"]) == 130
    assert capsys.readouterr().err == "vqtouch: interrupted\n"


def test_debug_is_a_global_flag(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    assert "--debug" in out and "VQTOUCH_DEBUG=1" in out


def test_the_default_demo_is_the_tour_of_every_stage_with_a_sample_grid_per_condition(tmp_path, capsys):
    """`vqtouch demo` (and `make demo`) runs the tour: tokenizer, real frames, families, adaptation and one
    generator from each of its four conditions, each condition shown with its own scores and samples."""
    out = tmp_path / "run"
    tiny = [
        *TINY_DEMO,
        "--set",
        "cluster.images_per_sensor=4",
        "--set",
        "cluster.variants_per_family=1",
        "--set",
        "adapt.steps=2",
        "--set",
        "adapt.shots=4",
        "--set",
        "adapt.eval_images=4",
        "--set",
        "generator.train.steps=2",
        "--set",
        "generator.train.checkpoint_every=2",
        "--set",
        "generator.num_samples=2",
        "--set",
        "generator.steps=2",
        "--set",
        "generator.model.depth=1",
        "--set",
        "generator.model.width=16",
        "--set",
        "generator.model.heads=2",
        "--set",
        "fewshot.generator_steps=2",
        "--set",
        "fewshot.samples=2",
        "--set",
        "fewshot.feature_size=32",
    ]
    assert main(["--no-progress", "demo", "--out", str(out), *tiny]) == 0
    # The bundled checkpoints work at 64 px: at this test's 32 px the pretrained stage says it cannot run.
    assert "scene tour: 6 of 7 stages ran, 1 cannot run" in capsys.readouterr().out
    stages = {s["stage"]: s for s in json.loads((out / "report.json").read_text())["stages"]}
    assert list(stages) == ["tokenizer", "reconstruct", "cluster", "adapt", "generator", "fewshot", "pretrained"]
    # The bundled generator, fine-tuned for the unseen GelSight on the adapt stage's tokenizer (the bundle's, adapted).
    fewshot = stages["fewshot"]["result"]
    assert fewshot["family_generator"] == "pretrained:tour" and fewshot["adapted_tokenizer"] == "the adapt stage's"
    assert "data.image_size: bundle 64, scene 32" in stages["pretrained"]["status"]
    parts = stages["generator"]["result"]["parts"]
    assert sorted(parts) == ["from label", "from tactile", "from text_scratch", "from visual"]
    for part in parts.values():
        assert "background_psnr" in part and (out / part["picture"]).is_file()
    assert len({part["picture"] for part in parts.values()}) == 4
    adapt = stages["adapt"]["result"]
    assert {"ssim", "before_ssim", "psnr", "before_psnr"} <= set(adapt)


def test_a_plugin_on_the_command_line_is_a_name_or_a_json_block():
    from vqtouch.plugins.cli.app import plugin_block

    assert plugin_block(" gelsight ", "--sensor") == {"name": "gelsight"}
    assert plugin_block('{"name": "digit", "view": "full"}', "--sensor") == {"name": "digit", "view": "full"}
    assert plugin_block('{"root": "frames"}', "--images", default_name="image_folder") == {
        "name": "image_folder",
        "root": "frames",
    }
    with pytest.raises(ConfigError, match="--sensor is not valid JSON"):
        plugin_block('{"name": ', "--sensor")
    with pytest.raises(ConfigError, match='--dataset: a JSON block needs the plugin\'s "name"'):
        plugin_block('{"root": "frames"}', "--dataset")

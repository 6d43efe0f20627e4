"""Bundled pretrained checkpoints: export, headers, fp16 storage, strict load, the ``pretrained`` stage."""

from __future__ import annotations

import json

import pytest
import torch
from safetensors import safe_open

from generator_runs import TINY, cluster_args, tiny_tokenizer_args, train_args
from vqtouch.core import Assembly, ConfigError, load_config_file, load_plugins, read_metadata, resolve_config
from vqtouch.plugins.runtime.execution import run_stage
from vqtouch.plugins.runtime.run_dir import RunDir
from vqtouch.plugins.cli.app import main
from vqtouch.plugins.generator.pipeline import load_pipeline
from vqtouch.plugins.tokenizer import tokenizer_digest
from vqtouch.plugins.pretrained import bundle as bundle_module
from vqtouch.plugins.pretrained.bundle import (
    COMMAND_KEY,
    RUN_CONFIG_KEY,
    bundle_folder,
    bundle_names,
    describe_bundle,
    export_bundle,
    half_precision_copy,
    load_bundle,
)

HOST = load_plugins()


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny trained label-to-touch run and its bundle under a private root."""
    root = tmp_path_factory.mktemp("pretrained")
    run = root / "run"
    assert main(train_args(run)) == 0
    bundles = root / "bundles"
    export_bundle(run, "tiny", HOST, root=bundles)
    return run, bundles


def scene_config(*extra: str):
    overrides = [*TINY, 'stages=["pretrained"]', "pretrained.num_samples=3", "pretrained.steps=3", *extra]
    return resolve_config("label-to-touch", (), overrides, host=HOST)


def test_headers_say_how_and_when_each_file_was_trained(trained):
    run, bundles = trained
    folder = bundles / "tiny"
    env, config = json.loads((run / "env.json").read_text()), json.loads((run / "config.json").read_text())
    pipe = load_pipeline(run, host=HOST)
    for path in sorted(folder.rglob("*.safetensors")):
        header = read_metadata(path)
        assert header[COMMAND_KEY].startswith(" ".join(env["argv"]))
        assert json.loads(header[RUN_CONFIG_KEY]) == config
    assert (
        int(read_metadata(folder / "generator" / "generator.safetensors")["vqtouch.step"])
        == pipe.generator.vqtouch_step
        == 6
    )
    facts = describe_bundle(folder)
    assert facts["conditioners"] == ["label"] and facts["files"] == 4 and facts["generator_step"] == 6
    assert facts["megabytes"] == round(sum(p.stat().st_size for p in folder.rglob("*.safetensors")) / 1e6, 2)


def test_a_bundle_trained_on_a_gpu_says_which(trained, tmp_path):
    """Minutes on a GPU are not minutes on a CPU: the command recorded names the device that ran it
    when that was not the CPU (the run's env.json), and says nothing more for a CPU run."""
    import shutil

    run, bundles = trained
    cpu_header = read_metadata(bundles / "tiny" / "generator" / "generator.safetensors")[COMMAND_KEY]
    assert json.loads((run / "env.json").read_text())["device_name"] == "cpu"
    assert " on " not in cpu_header.partition("#")[2]
    gpu_run = tmp_path / "gpu_run"
    shutil.copytree(run, gpu_run)
    env = json.loads((gpu_run / "env.json").read_text())
    (gpu_run / "env.json").write_text(json.dumps({**env, "device_name": "NVIDIA H200"}))
    folder = export_bundle(gpu_run, "tiny_gpu", HOST, root=tmp_path / "bundles")
    for path in sorted(folder.rglob("*.safetensors")):
        if path.parent.name == "generator":
            assert read_metadata(path)[COMMAND_KEY].endswith(" on NVIDIA H200")
    assert describe_bundle(folder)["generator_command"].endswith(" on NVIDIA H200")


def test_parameters_are_stored_in_fp16_except_the_quantizers_and_load_back_as_fp16_rounding(trained):
    run, bundles = trained
    folder = bundles / "tiny"
    with safe_open(str(folder / "generator" / "generator.safetensors"), "pt") as handle:
        dtypes = {handle.get_tensor(key).dtype for key in handle.keys()}
    assert torch.float16 in dtypes
    with safe_open(str(folder / "tokenizer" / "quantizer.safetensors"), "pt") as handle:
        assert all(handle.get_tensor(key).dtype != torch.float16 for key in handle.keys())
    original = load_pipeline(run, host=HOST)
    loaded = load_bundle("tiny", HOST, root=bundles)
    for mine, theirs in (
        (loaded.generator, original.generator),
        (loaded.tokenizer.autoencoder, original.tokenizer.autoencoder),
    ):
        for (name, value), (_, reference) in zip(mine.named_parameters(), theirs.named_parameters()):
            assert value.dtype == torch.float32
            assert torch.equal(value, reference.half().float()), name
    for value, reference in zip(loaded.tokenizer.quantizer.parameters(), original.tokenizer.quantizer.parameters()):
        assert torch.equal(value, reference)


def test_a_parameter_beyond_fp16_is_refused_not_stored_as_infinity():
    module = torch.nn.Linear(2, 2)
    with torch.no_grad():
        module.weight[0, 0] = 1e5
    with pytest.raises(ConfigError, match="beyond float16.*--precision fp32"):
        half_precision_copy(module, "x.safetensors")
    assert module.weight.dtype == torch.float32  # the original is untouched


def test_unknown_bundle_and_existing_bundle_are_one_line_errors(trained, tmp_path):
    run, bundles = trained
    with pytest.raises(ConfigError, match="no bundled checkpoints named 'nope'.*bundled: tiny") as caught:
        bundle_folder("nope", bundles)
    assert "\n" not in str(caught.value)
    with pytest.raises(ConfigError, match="exists; pass --overwrite"):
        export_bundle(run, "tiny", HOST, root=bundles)
    with pytest.raises(ConfigError, match="plain folder name"):
        export_bundle(run, "../x", HOST, root=bundles)


def test_the_stage_scores_the_bundle_on_another_datasets_held_out_split(trained, tmp_path, monkeypatch):
    _, bundles = trained
    monkeypatch.setattr(bundle_module, "BUNDLES", bundles)
    config = scene_config("pretrained.bundle=tiny", "data.dataset.seed=5")
    run = RunDir.create(config, host=HOST, path=tmp_path / "show")
    outcome = run_stage("pretrained", Assembly(config, HOST), run)
    assert outcome.status == "ran", outcome.describe()
    result = outcome.result
    assert result["bundled"] is True and result["generator_step"] == 6 and result["tokenizer_step"] == 2
    assert set(result["parts"]) == {"bundled tokenizer", "bundled generator from label"}
    for part in result["parts"].values():
        assert (run.path / part["picture"]).is_file()
        assert 0 < part["psnr"] < 100 and "background_psnr" in part
    assert result["parts"]["bundled generator from label"]["samples"] == 3


@pytest.mark.parametrize(
    "extra, reason",
    [
        (("data.dataset.seed=0",), "very dataset"),
        (("data.dataset.seed=5", "data.image_size=64"), "data.image_size: bundle 32, scene 64"),
        (("pretrained.bundle=missing",), "no bundled checkpoints named 'missing'"),
    ],
)
def test_the_stage_refuses_data_the_bundle_cannot_speak_for(trained, tmp_path, monkeypatch, extra, reason):
    _, bundles = trained
    monkeypatch.setattr(bundle_module, "BUNDLES", bundles)
    config = scene_config("pretrained.bundle=tiny", *extra)
    run = RunDir.create(config, host=HOST, path=tmp_path / "refused")
    outcome = run_stage("pretrained", Assembly(config, HOST), run)
    assert outcome.status == "unavailable" and reason in outcome.describe()


def test_list_command_prints_steps_and_commands(trained, capsys):
    _, bundles = trained
    assert main(["pretrained", "list", "--root", str(bundles), "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [row["name"] for row in rows] == ["tiny"] and "train generator" in rows[0]["generator_command"]


def test_a_plugin_can_serve_pretrained_names_through_its_hook(trained, make_plugin):
    """The generation pipeline opens `pretrained:NAME` through vqtouch_open_pretrained, so a plugin
    package can ship bundles, and the generator package never imports the one that ships the built-in."""
    from vqtouch.core import hookimpl

    _, bundles = trained

    @hookimpl
    def vqtouch_open_pretrained(name, host, device):
        return load_bundle("tiny", host, device=device, root=bundles) if name == "lab-tiny" else None

    host = load_plugins(autoload=False, extra=[make_plugin("lab_bundles", vqtouch_open_pretrained)])
    pipe = load_pipeline("pretrained:lab-tiny", host=host, device="cpu")
    assert pipe.run is None and pipe.checkpoint == bundles / "tiny" / "generator"
    # Other names still reach the built-in plugin's bundles.
    with pytest.raises(ConfigError, match="no bundled checkpoints named 'nope'"):
        load_pipeline("pretrained:nope", host=host, device="cpu")
    # With no plugin that ships bundles, one line says so.
    with pytest.raises(ConfigError, match="no installed plugin ships bundled weights") as error:
        load_pipeline("pretrained:tour", host=load_plugins(autoload=False, block=["pretrained"]), device="cpu")
    assert "\n" not in str(error.value)


def test_a_bundle_name_is_a_tokenizer_wherever_one_is_read(trained, tmp_path, monkeypatch, capsys):
    """`pretrained:NAME` as `train generator --tokenizer`, `reconstruct --run`, `cluster --run` and
    `evaluate reconstruction --run`: the bundle's tokenizer folder, as if that folder were given; the
    evaluation prints its scores and writes nothing into the read-only bundle."""
    _, bundles = trained
    monkeypatch.setattr(bundle_module, "BUNDLES", bundles)
    folder = bundles / "tiny" / "tokenizer"

    generator = tmp_path / "gen"
    assert main(train_args(generator, flags=("--tokenizer", "pretrained:tiny"))) == 0
    config = json.loads((generator / "config.json").read_text())
    assert config["generator"]["tokenizer_run"] == str(folder.resolve()) and config["stages"] == ["generator"]

    records = []
    for source, out in (("pretrained:tiny", tmp_path / "by_name"), (str(folder), tmp_path / "by_folder")):
        assert main(["reconstruct", "--run", source, "--real-frames", "gelsight", "--out", str(out)]) == 0
        records.append(json.loads((out / "reconstruct.json").read_text()))
    assert records[0] == records[1] and records[0]["checkpoint"] == str(folder)

    cluster = cluster_args("pretrained:tiny", tmp_path / "clusters", ["gelsight", "digit"], images=6, image_size=32)
    assert main(cluster) == 0
    summary = json.loads((tmp_path / "clusters" / "cluster.json").read_text())
    assert summary["tokenizer"] == str(folder.resolve()) and summary["tokenizer_sha256"] == tokenizer_digest(folder)

    before = sorted(path.name for path in folder.iterdir())
    capsys.readouterr()
    dataset = json.dumps({"name": "procedural", "num_samples": 6, "seed": 5})
    evaluate = ["--no-progress", "evaluate", "reconstruction", "--run", "pretrained:tiny", "--dataset", dataset]
    assert main([*evaluate, "--metrics", "ssim,psnr"]) == 0
    captured = capsys.readouterr()
    assert "pretrained:tiny is a bundle, read-only" in captured.err and f'"checkpoint": "{folder}"' in captured.out
    assert sorted(path.name for path in folder.iterdir()) == before
    assert main([*evaluate, "--step", "2"]) == 2 and "--step and --split choose within a run" in capsys.readouterr().err


@pytest.fixture(scope="module")
def tokenizer_bundle(tmp_path_factory):
    """A tiny tokenizer run trained from a recipe file in a private recipes folder, and its tokenizer bundle."""
    root = tmp_path_factory.mktemp("tokenizer_bundle")
    recipes = root / "recipes"
    recipes.mkdir()
    recipe = recipes / "tiny_tokenizer.toml"
    recipe.write_text('scene = "reconstruction"\n\n[tokenizer.train]\nsteps = 2\n')
    run = root / "run"
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(bundle_module, "RECIPES", recipes)
        assert main([*tiny_tokenizer_args(run), "--config", str(recipe)]) == 0
        export_bundle(run, "tok", HOST, root=root / "bundles")
    return run, root / "bundles", recipes


def test_a_tokenizer_run_makes_a_tokenizer_bundle_that_reads_like_its_run(tokenizer_bundle, monkeypatch, capsys):
    """Exported from `train tokenizer`: tokenizer files only; listed as a tokenizer bundle naming its
    recipe; its reconstructions those of the run up to fp16 storage; a generator read refused in one line."""
    from vqtouch.plugins.tokenizer import load_tokenizer

    run, bundles, recipes = tokenizer_bundle
    monkeypatch.setattr(bundle_module, "RECIPES", recipes)
    folder = bundles / "tok"
    assert sorted(str(path.relative_to(folder)) for path in folder.rglob("*.safetensors")) == [
        "tokenizer/autoencoder.safetensors",
        "tokenizer/quantizer.safetensors",
    ]
    assert bundle_names(bundles) == ["tok"]
    facts = describe_bundle(folder)
    assert facts["kind"] == "tokenizer" and facts["generator_step"] is None and facts["tokenizer_step"] == 2
    assert facts["recipes"] == {"tokenizer": "tiny_tokenizer.toml", "generator": None}
    assert "train tokenizer" in facts["tokenizer_command"]

    monkeypatch.setattr(bundle_module, "BUNDLES", bundles)
    images = torch.rand(2, 3, 32, 32, generator=torch.Generator().manual_seed(0))
    from_run, _ = load_tokenizer(run, HOST)
    from_bundle, _ = load_tokenizer("pretrained:tok", HOST)
    with torch.no_grad():
        torch.testing.assert_close(
            from_bundle.reconstruct(images)[0], from_run.reconstruct(images)[0], atol=0.02, rtol=0
        )
    with pytest.raises(ConfigError, match="pretrained:tok is a tokenizer bundle") as error:
        load_pipeline("pretrained:tok", host=HOST, device="cpu")
    assert "\n" not in str(error.value)

    assert main(["pretrained", "list", "--root", str(bundles)]) == 0
    printed = capsys.readouterr().out
    assert "tok: vqgan tokenizer step 2 (a tokenizer bundle)" in printed
    assert (
        f"tokenizer recipe: tiny_tokenizer.toml (vqtouch train tokenizer --config {recipes / 'tiny_tokenizer.toml'})"
        in printed
    )
    with pytest.raises(ConfigError, match="trained no generator"):
        export_bundle(run, "tok2", HOST, root=bundles, sampling={"steps": 3})


def test_a_run_not_trained_from_a_shipped_recipe_names_none(trained):
    _, bundles = trained
    assert describe_bundle(bundles / "tiny")["recipes"] == {"tokenizer": None, "generator": None}


@pytest.mark.parametrize("name", sorted(path.name for path in bundle_module.RECIPES.glob("*.toml")))
def test_every_shipped_recipe_validates_over_the_scene_it_names(name):
    recipe = bundle_module.RECIPES / name
    assert load_config_file(recipe).get("scene"), f"{name} names no scene"
    resolve_config(None, [recipe], host=HOST)


@pytest.mark.parametrize("name", bundle_names())
def test_every_shipped_bundle_names_a_shipped_recipe_or_none(name):
    for recipe in describe_bundle(bundle_folder(name))["recipes"].values():
        assert recipe is None or (bundle_module.RECIPES / recipe).is_file()


@pytest.mark.parametrize(
    "name", [name for name in bundle_names() if describe_bundle(bundle_folder(name))["kind"] == "generator"]
)
def test_every_shipped_bundle_draws_from_a_label_and_stays_within_50_mb(name, tmp_path):
    """What the package ships: each bundle opens with today's plugins (a header its run's plugin no longer
    reads would fail here, not in a user's first command), draws an image end to end, and keeps to the
    size a package can carry."""
    import numpy as np
    from PIL import Image

    facts = describe_bundle(bundle_folder(name))
    assert facts["megabytes"] <= 50, f"bundle {name} is {facts['megabytes']} MB"
    assert "label" in facts["conditioners"]
    out = tmp_path / name
    command = ["--no-progress", "--threads", "1", "generate", "--run", f"pretrained:{name}", "--label", "0"]
    assert main([*command, "--steps", "2", "--seed", "0", "--out", str(out)]) == 0
    assert json.loads((out / "generate.json").read_text())["checkpoint"] == str(bundle_folder(name) / "generator")
    pixels = np.asarray(Image.open(out / "sample_0000.png"), dtype=np.float32)
    assert pixels.shape[:2] == (64, 64) and pixels.std() > 1.0


def _bundles_of_kind(kind: str) -> list[str]:
    return [name for name in bundle_names() if describe_bundle(bundle_folder(name))["kind"] == kind]


@pytest.mark.parametrize("name", _bundles_of_kind("tokenizer"))
def test_every_shipped_tokenizer_bundle_reconstructs_the_scene_it_was_trained_on(name):
    """A shipped tokenizer bundle opens by name with today's plugins, names a shipped recipe, stays small,
    and reconstructs images of its recipe's scene (another dataset seed) far better than their mean image."""
    from vqtouch.plugins.tokenizer import load_tokenizer

    facts = describe_bundle(bundle_folder(name))
    assert facts["megabytes"] <= 20 and facts["recipes"]["tokenizer"] is not None
    config = resolve_config(None, [bundle_module.RECIPES / facts["recipes"]["tokenizer"]], host=HOST)
    dataset = Assembly(config, HOST).build(
        "dataset", {**config.data.dataset.model_dump(), "seed": 12345, "num_samples": 8}
    )
    images = torch.stack([dataset[i]["tactile"] for i in range(8)]).float()
    tokenizer, _ = load_tokenizer(f"pretrained:{name}", HOST)
    with torch.no_grad():
        reconstruction = tokenizer.reconstruct(images)[0].float()
    assert torch.isfinite(reconstruction).all()
    error = (reconstruction - images).pow(2).mean()
    mean_image_error = (images.mean(0, keepdim=True) - images).pow(2).mean()
    psnr = -10 * torch.log10(error)
    # The mean image already scores about 32 dB on these mostly flat frames: ask for 6 dB (a quarter of its error) more.
    assert psnr > 36 and error < mean_image_error / 4, f"{name}: {psnr:.1f} dB"

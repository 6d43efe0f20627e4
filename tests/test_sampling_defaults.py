"""Sampling with the weights' moving average and per-conditioner guidance defaults.

A tiny label-to-touch generator trained with ``generator.train.ema_decay`` samples with the EMA
the trainer saved (unless ``--weights raw``), exports it into bundles that say so, and takes its
guidance from ``generator.conditioner_guidance`` wherever no ``--guidance`` is given."""

import json

import pytest
import torch
from safetensors.torch import load_file

from vqtouch.core import CheckpointError, ConfigError, load_plugins, validate_experiment
from vqtouch.plugins.cli.app import main
from vqtouch.plugins.training.checkpoints import TRAINER_STATE, apply_ema_weights, saved_ema_weights
from vqtouch.plugins.generator import load_pipeline
from vqtouch.plugins.pretrained.bundle import describe_bundle, export_bundle, load_bundle

from cli_checks import one_error_line
from generator_runs import TINY, train_args

HOST = load_plugins(autoload=False)


def generator_args(out, tokenizer, *extra):
    overrides = [o for o in TINY if not o.startswith("tokenizer.")] + list(extra)
    args = ["--no-progress", "train", "generator", "--scene", "label-to-touch", "--tokenizer", str(tokenizer)]
    args += ["--out", str(out)]
    for override in overrides:
        args += ["--set", override]
    return args


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A tiny run without an EMA (tokenizer + generator), and a generator with one (decay 0.5) and a
    guidance of 3 for its label conditioner, on the first run's tokenizer."""
    root = tmp_path_factory.mktemp("sampling_defaults")
    plain = root / "plain"
    assert main(train_args(plain)) == 0
    averaged = root / "ema"
    extra = ("generator.train.ema_decay=0.5", 'generator.conditioner_guidance={"label": 3}')
    assert main(generator_args(averaged, plain, *extra)) == 0
    return plain, averaged


def newest_step(run):
    return sorted((run / "checkpoints" / "generator").iterdir())[-1]


def test_the_pipeline_samples_with_the_saved_average_unless_raw_is_asked(runs):
    _, run = runs
    folder = newest_step(run)
    raw_file = load_file(str(folder / "generator.safetensors"))
    # Read straight from the trainer state, independently of saved_ema_weights.
    state = load_file(str(folder / TRAINER_STATE))
    average = {
        key.removeprefix("ema.generator."): value for key, value in state.items() if key.startswith("ema.generator.")
    }
    assert average and any(not torch.equal(average[key], raw_file[key]) for key in average)

    pipe = load_pipeline(run, host=HOST)
    assert pipe.settings["weights"] == "ema"
    loaded = pipe.generator.state_dict()
    assert all(torch.equal(loaded[key], value) for key, value in average.items())

    raw = load_pipeline(run, host=HOST, weights="raw")
    assert raw.settings["weights"] == "raw"
    assert all(torch.equal(raw.generator.state_dict()[key], value) for key, value in raw_file.items())
    assert not torch.equal(pipe(label=1, n=2, steps=3, seed=4), raw(label=1, n=2, steps=3, seed=4))


def test_the_stage_scores_the_weights_readers_load(runs):
    plain, run = runs
    assert json.loads((run / "generation.json").read_text())["sample_weights"] == "ema"
    assert "sample_weights" not in json.loads((plain / "generation.json").read_text())
    assert load_pipeline(plain, host=HOST).settings["weights"] == "raw"


def test_asking_for_an_average_a_run_never_kept_is_one_line(runs, tmp_path, capsys):
    plain, _ = runs
    with pytest.raises(ConfigError, match="holds no EMA weights"):
        load_pipeline(plain, host=HOST, weights="ema")
    out = tmp_path / "gen"
    assert main(["generate", "--run", str(plain), "--label", "1", "--weights", "ema", "--out", str(out)]) == 2
    assert "holds no EMA weights" in one_error_line(capsys) and not out.exists()


def test_guidance_defaults_to_the_conditioners_own(runs, tmp_path, monkeypatch):
    _, run = runs
    pipe = load_pipeline(run, host=HOST)
    assert pipe.guidance_for(0) == 3.0 and pipe.settings["guidance"] == 1.0
    # A 6-step model's conditional and unconditional predictions nearly agree, so the samples cannot
    # tell guidance scales apart: the scale the generator is asked to sample with can.
    asked = []
    sample = pipe.generator.sample
    monkeypatch.setattr(pipe.generator, "sample", lambda *a, **k: asked.append(k["guidance"]) or sample(*a, **k))
    pipe(label=2, n=2, steps=3, seed=1)
    pipe(label=2, n=2, steps=3, seed=1, guidance=1.0)
    assert asked == [3.0, 1.0]
    out = tmp_path / "gen"
    assert main(["generate", "--run", str(run), "--label", "2", "--steps", "3", "--out", str(out)]) == 0
    written = json.loads((out / "generate.json").read_text())
    assert written["guidance"] == 3.0 and written["weights"] == "ema"


def test_a_guidance_for_a_conditioner_the_generator_lacks_is_refused(runs, tmp_path, capsys):
    plain, _ = runs
    out = tmp_path / "never"
    args = generator_args(out, plain, 'generator.conditioner_guidance={"visual": 2}')
    assert main(args) == 2
    line = one_error_line(capsys)
    assert "conditioner_guidance names 'visual'" in line and "label" in line and not out.exists()


def test_bundles_hold_the_average_and_say_so(runs, tmp_path):
    plain, run = runs
    export_bundle(run, "avg", HOST, root=tmp_path, precision="fp32")
    export_bundle(plain, "plain", HOST, root=tmp_path, precision="fp32")
    assert describe_bundle(tmp_path / "avg")["weights"] == "ema"
    assert describe_bundle(tmp_path / "plain")["weights"] == "raw"
    bundle = load_bundle("avg", HOST, root=tmp_path)
    average = saved_ema_weights(newest_step(run))["generator"]
    recorded = validate_experiment(bundle.run_config, HOST).generator
    assert bundle.weights == "ema" and recorded.guidance_for("label") == 3.0
    assert all(torch.equal(bundle.generator.state_dict()[key], value) for key, value in average.items())


def test_export_bundles_the_raw_weights_of_an_averaged_run_when_asked(runs, tmp_path, capsys):
    plain, run = runs
    export = ["pretrained", "export", "--run", str(run), "--name", "raw", "--root", str(tmp_path)]
    assert main([*export, "--weights", "raw", "--precision", "fp32"]) == 0
    assert describe_bundle(tmp_path / "raw")["weights"] == "raw"
    bundled = load_bundle("raw", HOST, root=tmp_path).generator.state_dict()
    # Read straight from the checkpoint's module file, independently of the loading path export uses.
    raw_file = load_file(str(newest_step(run) / "generator.safetensors"))
    average = saved_ema_weights(newest_step(run))["generator"]
    assert raw_file and all(torch.equal(bundled[key], value) for key, value in raw_file.items())
    assert any(not torch.equal(raw_file[key], value) for key, value in average.items())
    capsys.readouterr()
    args = ["pretrained", "export", "--run", str(plain), "--name", "none", "--weights", "ema", "--root", str(tmp_path)]
    assert main(args) == 2
    assert "holds no EMA weights" in one_error_line(capsys) and not (tmp_path / "none").exists()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda ema: ema.pop(next(iter(ema))), "missing"),
        (lambda ema: ema.update(extra=torch.zeros(1)), "unexpected 'extra'"),
        (lambda ema: ema.update({k: torch.zeros(3, 3) for k in list(ema)[:1]}), "has shape"),
        (lambda ema: ema.update({k: v.clone().fill_(float("nan")) for k, v in list(ema.items())[-1:]}), "NaN or Inf"),
    ],
)
def test_an_average_that_does_not_fit_replaces_nothing_silently(change, message):
    module = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.LayerNorm(4))
    ema = {key: value.clone() + 1 for key, value in module.state_dict().items()}
    change(ema)
    before = {key: value.clone() for key, value in module.state_dict().items()}
    with pytest.raises(CheckpointError, match=message):
        apply_ema_weights(module, ema, "where")
    assert all(torch.equal(module.state_dict()[key], value) for key, value in before.items())


def test_integer_buffers_keep_their_values():
    module = torch.nn.BatchNorm1d(3)
    module.num_batches_tracked.fill_(7)
    floating = {k: v.clone() + 2 for k, v in module.state_dict().items() if v.dtype.is_floating_point}
    apply_ema_weights(module, floating, "where")
    assert module.num_batches_tracked.item() == 7 and torch.equal(module.weight.detach(), torch.full((3,), 3.0))


def test_the_stage_scores_match_a_rescoring_with_the_average_not_the_raw_weights(runs, tmp_path, capsys):
    _, run = runs
    stage = json.loads((run / "generation.json").read_text())
    scored = {}
    for weights in ("ema", "raw"):
        out = tmp_path / weights
        args = ["evaluate", "generation", "--run", str(run), "--n", "4", "--weights", weights, "--out", str(out)]
        assert main(args) == 0
        scored[weights] = json.loads((out / "generation.json").read_text())["by_conditioner"]["0:label"]
    capsys.readouterr()
    assert scored["ema"]["psnr"] == stage["psnr"] and scored["raw"]["psnr"] != stage["psnr"]


def test_a_bundle_may_set_its_own_sampling_defaults_and_its_headers_say_so(runs, tmp_path, capsys):
    from vqtouch.plugins.pretrained.bundle import RUN_CONFIG_KEY, SAMPLING_KEY
    from vqtouch.core import read_metadata

    plain, _ = runs
    sampling = {"conditioner_guidance": {"label": 2.5}, "steps": 3}
    export_bundle(plain, "tuned", HOST, root=tmp_path, sampling=sampling)
    header = read_metadata(tmp_path / "tuned" / "generator" / "generator.safetensors")
    recorded = json.loads(header[RUN_CONFIG_KEY])["generator"]
    assert json.loads(header[SAMPLING_KEY]) == sampling
    assert recorded["conditioner_guidance"] == {"label": 2.5} and recorded["steps"] == 3
    assert recorded["train"] == json.loads((plain / "config.json").read_text())["generator"]["train"]
    bundle = load_bundle("tuned", HOST, root=tmp_path)
    assert validate_experiment(bundle.run_config, HOST).generator.guidance_for("label") == 2.5
    assert describe_bundle(tmp_path / "tuned")["sampling_defaults"] == sampling
    with pytest.raises(ConfigError, match="a bundle sets only its sampling defaults"):
        export_bundle(plain, "bad", HOST, root=tmp_path, sampling={"train": {"steps": 1}})
    with pytest.raises(ConfigError, match="conditioner_guidance names 'visual'"):
        export_bundle(plain, "bad", HOST, root=tmp_path, sampling={"conditioner_guidance": {"visual": 2}})
    assert not (tmp_path / "bad").exists()
    args = [
        "pretrained",
        "export",
        "--run",
        str(plain),
        "--name",
        "x",
        "--root",
        str(tmp_path),
        "--sampling",
        "guidance",
    ]
    assert main(args) == 2
    assert "--sampling 'guidance': give KEY=JSON" in one_error_line(capsys)


def test_the_pretrained_stage_samples_each_conditioner_at_the_bundles_default(runs, tmp_path, monkeypatch):
    from vqtouch.core import Assembly, resolve_config
    from vqtouch.plugins.runtime.execution import run_stage
    from vqtouch.plugins.runtime.run_dir import RunDir
    from vqtouch.plugins.pretrained import bundle as bundle_module
    from vqtouch.plugins.pretrained import stage as stage_module

    plain, _ = runs
    export_bundle(plain, "tuned", HOST, root=tmp_path / "bundles", sampling={"conditioner_guidance": {"label": 2.5}})
    monkeypatch.setattr(bundle_module, "BUNDLES", tmp_path / "bundles")
    asked = []
    score = stage_module.score_generation
    monkeypatch.setattr(stage_module, "score_generation", lambda **k: asked.append(k["guidance"]) or score(**k))
    overrides = [*TINY, 'stages=["pretrained"]', "pretrained.bundle=tuned", "pretrained.num_samples=2"]
    config = resolve_config("label-to-touch", (), [*overrides, "pretrained.steps=2", "data.dataset.seed=5"], host=HOST)
    outcome = run_stage("pretrained", Assembly(config, HOST), RunDir.create(config, host=HOST, path=tmp_path / "r"))
    assert outcome.status == "ran", outcome.describe()
    assert asked == [2.5]

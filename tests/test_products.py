"""Stages hand what they made to later stages through the run: ``makes`` in the registration,
``job.publish`` in the stage, ``run.product`` in the reader (plugins/runtime/run_dir.py, core/stages.py)."""

from __future__ import annotations

import json
import shutil

import pytest
import torch
from generator_runs import train_args

from vqtouch.core import Assembly, ConfigError, PluginError, hookimpl, load, load_plugins, resolve_config, save
from vqtouch.plugins.runtime.execution import run_stage
from vqtouch.plugins.runtime.run_dir import MissingProductError, PRODUCTS_FILE, RunDir
from vqtouch.plugins.cli.app import main


def _atlas_stage(job):
    """A stage that writes a folder and publishes it."""
    (job.run.path / "atlas").mkdir(exist_ok=True)
    (job.run.path / "atlas" / "atlas.txt").write_text("made\n")
    job.publish("atlas", "atlas", pages=3)
    return {}


def _reader_stage(job):
    return {"pages": job.product("atlas").facts["pages"]}


def _rogue_stage(job):
    (job.run.path / "rogue.txt").write_text("x")
    job.publish("atlas", "rogue.txt")


def _host(make_plugin, **stages):
    @hookimpl
    def vqtouch_register_stages(register):
        for name, (run, makes) in stages.items():
            register(name, run, needs=("sensor",), makes=makes, description=f"test stage {name}")

    return load_plugins(autoload=False, extra=[make_plugin("product_stages", vqtouch_register_stages)])


def _run(host, tmp_path, stages):
    config = resolve_config("reconstruction", host=host, overrides=[f"stages={json.dumps(stages)}"])
    assembly = Assembly(config, host)
    run = RunDir.create(config, host=host, path=tmp_path / "run")
    return run, [run_stage(stage, assembly, run) for stage in stages]


def test_a_published_product_is_what_a_later_stage_reads(make_plugin, tmp_path):
    host = _host(make_plugin, atlas=(_atlas_stage, ("atlas",)), reader=(_reader_stage, ()))
    run, outcomes = _run(host, tmp_path, ["atlas", "reader"])
    assert [outcome.status for outcome in outcomes] == ["ran", "ran"]
    assert outcomes[1].result == {"pages": 3}
    product = RunDir.open(run.path).product("atlas", host)
    assert (product.stage, product.path, product.facts) == ("atlas", run.path / "atlas", {"pages": 3})
    # Recorded relative to the run: a moved run still finds its products.
    moved = shutil.copytree(run.path, tmp_path / "moved")
    assert RunDir.open(moved).product("atlas").path == moved / "atlas"


def test_a_missing_product_names_the_stage_that_makes_it(make_plugin, tmp_path):
    host = _host(make_plugin, atlas=(_atlas_stage, ("atlas",)), reader=(_reader_stage, ()))
    run, outcomes = _run(host, tmp_path, ["reader"])
    assert outcomes[0].status == "failed"
    assert "no 'atlas' in this run (it holds nothing yet); the 'atlas' stage makes it" in outcomes[0].reason
    with pytest.raises(
        MissingProductError, match="unknown product 'atlsa'; available: .*atlas.*; did you mean 'atlas'"
    ):
        run.product("atlsa", host)


def test_a_product_whose_file_is_gone_is_refused(make_plugin, tmp_path):
    host = _host(make_plugin, atlas=(_atlas_stage, ("atlas",)))
    run, _ = _run(host, tmp_path, ["atlas"])
    shutil.rmtree(run.path / "atlas")
    with pytest.raises(MissingProductError, match="the 'atlas' that stage 'atlas' made is gone"):
        run.product("atlas", host)


def test_a_stage_publishes_only_what_it_declares(make_plugin, tmp_path):
    host = _host(make_plugin, rogue=(_rogue_stage, ()))
    _, [outcome] = _run(host, tmp_path, ["rogue"])
    assert outcome.status == "failed"
    assert (
        "stage 'rogue' published 'atlas' but declares makes=none; add it to the stage's registration" in outcome.reason
    )
    assert not (tmp_path / "run" / PRODUCTS_FILE).exists()


def test_a_product_has_one_maker(make_plugin):
    with pytest.raises(PluginError, match="makes product 'atlas', which stage 'atlas' .* already makes"):
        _host(make_plugin, atlas=(_atlas_stage, ("atlas",)), copy=(_atlas_stage, ("atlas",)))


def test_publish_refuses_paths_outside_the_run_and_unwritten_ones(make_plugin, tmp_path):
    host = _host(make_plugin, atlas=(_atlas_stage, ("atlas",)))
    run, _ = _run(host, tmp_path, ["atlas"])
    (tmp_path / "elsewhere.txt").write_text("x")
    with pytest.raises(ValueError, match="is outside the run"):
        run.publish("atlas", tmp_path / "elsewhere.txt", stage="atlas")
    with pytest.raises(ValueError, match="does not exist; publish a product after writing it"):
        run.publish("atlas", "not-written", stage="atlas")
    assert run.product("atlas").path == run.path / "atlas"  # the refused calls left the index as it was


def test_a_damaged_products_index_is_named(make_plugin, tmp_path):
    host = _host(make_plugin, atlas=(_atlas_stage, ("atlas",)))
    run, _ = _run(host, tmp_path, ["atlas"])
    (run.path / PRODUCTS_FILE).write_text('{"atlas": "atlas"}')
    with pytest.raises(
        ConfigError,
        match=r"products.json \(product 'atlas'\): input should be a valid dictionary or instance of ProductEntry",
    ):
        run.product("atlas")


def test_the_built_in_stages_declare_their_products(host):
    makers = {product: stage.name for stage in host.stages.values() for product in stage.makes}
    assert {
        "tokenizer": "tokenizer",
        "families": "cluster",
        "adapted_tokenizer": "adapt",
        "generator": "generator",
    }.items() <= makers.items()


def test_a_generator_keeps_the_tokenizer_it_was_trained_on(tmp_path, host):
    """The generator product pins the tokenizer step folder: a tokenizer that trains on afterwards (a
    newer step folder) does not replace it under the generator."""
    from vqtouch.plugins.generator import load_pipeline

    out = tmp_path / "run"
    assert main(train_args(out)) == 0
    run = RunDir.open(out)
    products = run.products()
    trained_on = products["tokenizer"].path
    assert products["generator"].facts["tokenizer"] == trained_on.relative_to(out).as_posix()
    assert products["generator"].path.parent == out / "checkpoints" / "generator"
    # The tokenizer "trains on": a newer, complete step folder with other weights.
    newer = out / "checkpoints" / "step-00000099"
    shutil.copytree(trained_on, newer)
    autoencoder = load(trained_on / "autoencoder.safetensors", host=host)
    with torch.no_grad():
        for parameter in autoencoder.parameters():
            parameter.add_(1.0)
    save(autoencoder, newer / "autoencoder.safetensors", step=99, host=host)
    pipe = load_pipeline(out, host=host, device="cpu")
    expected = load(trained_on / "autoencoder.safetensors", host=host).state_dict()
    loaded = pipe.tokenizer.autoencoder.state_dict()
    assert all(torch.equal(loaded[key], value) for key, value in expected.items())
    # Its folder gone, the generator's tokenizer is refused rather than replaced by the newer one.
    shutil.rmtree(trained_on)
    with pytest.raises(Exception, match="its generator was trained on the tokenizer in .*, which is gone"):
        load_pipeline(out, host=host, device="cpu")


def test_products_of_a_run_given_by_a_relative_path(make_plugin, tmp_path, monkeypatch):
    """``make demo`` writes runs/demo: a path built from the run's own (``job.run.path / ...``, a
    trainer's step folder) is relative to the working directory, not to the run, and must not be
    joined to the run's path a second time."""

    def built_from_the_run(job):
        (job.run.path / "atlas").mkdir()
        job.publish("atlas", job.run.path / "atlas")
        return {}

    host = _host(make_plugin, atlas=(built_from_the_run, ("atlas",)))
    monkeypatch.chdir(tmp_path)
    config = resolve_config("reconstruction", overrides=['stages=["atlas"]'], host=host)
    run = RunDir.create(config, host=host, path="runs/demo")
    outcome = run_stage("atlas", Assembly(config, host), run)
    assert outcome.status == "ran", outcome.reason
    assert run.product("atlas").path.resolve() == (tmp_path / "runs" / "demo" / "atlas").resolve()
    assert json.loads((tmp_path / "runs" / "demo" / "products.json").read_text())["atlas"]["path"] == "atlas"

"""bench/gpu_generator.py, the generator's check on a lent GPU: what it trains (the bundle's own
recipe) and what it brings back (runs that can be scored once unpacked, with the originals intact)."""

from __future__ import annotations

import hashlib
import importlib.util
import json
import shlex
import tarfile
from pathlib import Path

import pytest
import torch
from generator_runs import train_args
from safetensors import safe_open
from safetensors.torch import load_file

from vqtouch.plugins.cli.app import main
from vqtouch.core.plugin_manager import load_plugins
from vqtouch.plugins.training.checkpoints import latest_good_checkpoint
from vqtouch.plugins.generator.pipeline import load_pipeline
from vqtouch.plugins.pretrained.bundle import RECIPES, bundle_folder, describe_bundle

REPO = Path(__file__).resolve().parents[1]
HOST = load_plugins(autoload=False)


def _bench():
    spec = importlib.util.spec_from_file_location("gpu_generator", REPO / "bench" / "gpu_generator.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _digests(folder: Path) -> dict[str, str]:
    return {
        str(path.relative_to(folder)): hashlib.sha256(path.read_bytes()).hexdigest()
        for path in sorted(folder.rglob("*.safetensors"))
    }


@pytest.mark.parametrize("bundle", ["tour", "tour_wide"])
def test_the_recipe_is_the_bundles_command_less_steps_and_batch_plus_its_sampling_defaults(bundle):
    """A bundle trained from a recipe file gives that file; one trained with --set values gives them,
    less what the script sets itself."""
    facts = describe_bundle(bundle_folder(bundle))
    recipe = _bench().bundle_recipe(bundle)
    if facts["recipes"]["generator"]:  # the shipped recipe file first, as the bundle was trained
        assert recipe[:2] == ["--config", str(RECIPES / facts["recipes"]["generator"])]
        assert (RECIPES / facts["recipes"]["generator"]).is_file()
        recipe = recipe[2:]
    assert recipe[::2] == ["--set"] * (len(recipe) // 2)
    values = recipe[1::2]
    words = shlex.split(facts["generator_command"].split("#")[0])
    command_values = [words[i + 1] for i, word in enumerate(words) if word == "--set"]
    dropped = [value for value in command_values if value not in values]
    # What the check sets itself is dropped, and nothing else.
    own = {"data.batch_size", "generator.train.steps", "generator.train.checkpoint_every", "generator.train.log_every"}
    assert {value.split("=")[0] for value in dropped} <= own
    assert [value for value in command_values if value in values] == [
        value for value in command_values if value.split("=")[0] not in own
    ]
    # The sampling defaults set at export are added (the command's own guidance, if any, is kept above).
    added = [value for value in values if value not in command_values]
    guidance = [value for value in added if value.startswith("generator.conditioner_guidance=")]
    assert added == guidance
    exported = facts["sampling_defaults"].get("conditioner_guidance")
    assert len(guidance) == (1 if exported else 0)
    if exported:
        assert json.loads(guidance[0].split("=", 1)[1]) == exported


@pytest.fixture(scope="module")
def packed(tmp_path_factory):
    """A tiny trained run (tokenizer and generator) in a work folder, packed as the script packs."""
    root = tmp_path_factory.mktemp("gpu_pack")
    work, logs, out = root / "work", root / "logs", root / "out"
    for folder in (work, logs, out):
        folder.mkdir()
    run = work / "gen"
    assert main(train_args(run)) == 0
    before = _digests(run)
    _bench().pack(work, logs, out, {"jobs": ["gen"]})
    unpacked = root / "unpacked"
    with tarfile.open(out / "weights_gen.tgz") as archive:
        archive.extractall(unpacked, filter="data")
    return run, before, unpacked / "gen", out


def test_packing_leaves_the_run_it_packs_as_it_was(packed):
    run, before, _, _ = packed
    # A generator pins its tokenizer's files by digest: changing them in place breaks its scoring.
    assert _digests(run) == before
    load_pipeline(run, host=HOST)


def test_the_packed_run_is_complete_and_scores_with_the_weights_it_was_trained_to(packed):
    run, _, unpacked, out = packed
    assert (out / "results.tgz").is_file()
    folder = latest_good_checkpoint(unpacked / "checkpoints" / "generator")
    assert folder is not None, "the trainer state marks a step folder complete; it must travel"
    with safe_open(str(folder / "trainer_state.safetensors"), "pt") as handle:
        assert not [key for key in handle.keys() if key.startswith("optim.")]
    source = load_file(str(latest_good_checkpoint(run / "checkpoints" / "generator") / "generator.safetensors"))
    copy = load_file(str(folder / "generator.safetensors"))
    assert copy.keys() == source.keys()
    for key, value in source.items():
        if value.dtype == torch.float32:
            assert copy[key].dtype == torch.float16
            torch.testing.assert_close(copy[key].float(), value, rtol=1e-3, atol=1e-4)
    # The tokenizer travels exact (its codes depend on the codebook's exact values).
    tokenizer = latest_good_checkpoint(run / "checkpoints")  # a run's tokenizer: checkpoints/step-N
    for name in ("autoencoder.safetensors", "quantizer.safetensors"):
        copied = unpacked / tokenizer.relative_to(run) / name
        assert copied.read_bytes() == (tokenizer / name).read_bytes()
    pipe = load_pipeline(unpacked, host=HOST)
    assert pipe.checkpoint.name == folder.name

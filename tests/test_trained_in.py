"""A run records the precision its components trained in (``precision: auto`` resolved for the device),
in every checkpoint's header, and a bundle exported from it carries that to ``vqtouch pretrained list``."""

from __future__ import annotations

import json

import generator_runs

from vqtouch.core import load, load_plugins, read_metadata
from vqtouch.core.checkpoint import TRAINED_IN_KEY
from vqtouch.plugins.cli.app import main
from vqtouch.plugins.training.precision import cpu_has_bf16_matrix_units
from vqtouch.plugins.training.checkpoints import latest_checkpoint
from vqtouch.plugins.pretrained.bundle import describe_bundle

HOST = load_plugins()


def test_checkpoints_and_bundles_name_the_precision_auto_resolved_to(tiny_label_run, tmp_path, capsys):
    # auto on a CPU: both in bf16 where the CPU has bf16 matrix units, else fp32 (the fixture's tokenizer
    # stage leaves its precision at auto).
    generator_precision = tokenizer_precision = "bf16" if cpu_has_bf16_matrix_units() else "fp32"
    tokenizer = latest_checkpoint(tiny_label_run / "checkpoints")
    generator = latest_checkpoint(tiny_label_run / "checkpoints" / "generator")
    for folder, precision in ((tokenizer, tokenizer_precision), (generator, generator_precision)):
        files = sorted(path for path in folder.glob("*.safetensors") if path.name != "trainer_state.safetensors")
        assert files and {read_metadata(path)[TRAINED_IN_KEY] for path in files} == {precision}
    assert load(tokenizer / "autoencoder.safetensors", host=HOST).vqtouch_trained_in == tokenizer_precision
    # The run's records say it too: eval.json (the tokenizer stage) and generation.json (the generator's).
    assert json.loads((tiny_label_run / "eval.json").read_text())["trained_in"] == tokenizer_precision
    assert json.loads((tiny_label_run / "generation.json").read_text())["trained_in"] == generator_precision
    export = ["pretrained", "export", "--run", str(tiny_label_run), "--name", "tiny", "--root", str(tmp_path)]
    assert main([*export, "--weights", "raw"]) == 0
    expected = {"tokenizer": tokenizer_precision, "generator": generator_precision}
    assert describe_bundle(tmp_path / "tiny")["trained_in"] == expected
    capsys.readouterr()
    assert main(["pretrained", "list", "--root", str(tmp_path)]) == 0
    assert f"  trained in: tokenizer {tokenizer_precision}, generator {generator_precision}" in capsys.readouterr().out


def test_a_run_forced_to_bf16_says_so(tmp_path):
    out = tmp_path / "tok"
    assert main([*generator_runs.tiny_tokenizer_args(out), "--set", "tokenizer.train.precision=bf16"]) == 0
    folder = latest_checkpoint(out / "checkpoints")
    assert read_metadata(folder / "autoencoder.safetensors")[TRAINED_IN_KEY] == "bf16"

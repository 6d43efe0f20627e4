"""Fault injection on the generation commands (issue 25): no command destroys what it reads, a generator
keeps the tokenizer it was trained on, NaN weights are refused in one line, ``generate --out`` is a
protected output.  Each case here once lost data or wrote a silently wrong result."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import torch
from generator_runs import tiny_tokenizer_args, train_args
from safetensors import safe_open
from safetensors.torch import save_file

from vqtouch.core.cli import main


def one_error_line(capsys) -> str:
    """The single stderr line of a failed command, without its prefix (asserts it is one line)."""
    err = capsys.readouterr().err
    assert err.startswith("vqtouch: error: ") and err.count("\n") == 1, err
    return err[len("vqtouch: error: ") :].rstrip("\n")


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` and its bytes."""
    return {str(path.relative_to(folder)): path.read_bytes() for path in sorted(folder.rglob("*")) if path.is_file()}


def poison(path: Path) -> None:
    """Replace every floating tensor of a safetensors file by NaN, keeping its header."""
    with safe_open(str(path), framework="pt") as handle:
        header = handle.metadata()
        tensors = {key: handle.get_tensor(key) for key in handle.keys()}
    save_file(
        {
            key: torch.full_like(value, float("nan")) if value.is_floating_point() else value
            for key, value in tensors.items()
        },
        str(path),
        metadata=header,
    )


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny tokenizer run TOK and a generator run GEN trained on it with ``--tokenizer TOK``."""
    root = tmp_path_factory.mktemp("faults")
    tok, gen = root / "tok", root / "gen"
    assert main(tiny_tokenizer_args(tok)) == 0
    assert main(train_args(gen, flags=("--tokenizer", str(tok)))) == 0
    return tok, gen


def generate(run: Path, out: Path, *extra: str) -> int:
    return main(
        [
            "--no-progress",
            "generate",
            "--run",
            str(run),
            "--label",
            "0",
            "--n",
            "2",
            "--steps",
            "2",
            "--out",
            str(out),
            *extra,
        ]
    )


# -- 1. a command never destroys the input it reads ----------------------------------------------


def test_train_generator_refuses_to_overwrite_the_tokenizer_it_reads(trained, capsys):
    tok, _ = trained
    before = snapshot(tok)
    assert main([*train_args(tok, flags=("--tokenizer", str(tok), "--overwrite"))]) == 2
    assert one_error_line(capsys) == (
        f"--out {tok} is the tokenizer run this command reads (--tokenizer); choose another --out"
    )
    assert snapshot(tok) == before


def test_train_generator_refuses_an_out_that_holds_its_tokenizer(trained, tmp_path, capsys):
    tok, _ = trained
    parent = tmp_path / "parent"
    inside = Path(shutil.copytree(tok, parent / "tok"))
    before = snapshot(parent)
    assert main([*train_args(parent, flags=("--tokenizer", str(inside), "--overwrite"))]) == 2
    assert f"holds the tokenizer run this command reads (--tokenizer: {inside}); choose" in one_error_line(capsys)
    assert snapshot(parent) == before


# -- 2. a generator run pins its tokenizer --------------------------------------------------------


def test_generate_refuses_a_retrained_tokenizer(tmp_path, capsys):
    tok, gen = tmp_path / "tok", tmp_path / "gen"
    assert main(tiny_tokenizer_args(tok)) == 0
    assert main(train_args(gen, flags=("--tokenizer", str(tok)))) == 0
    assert generate(gen, tmp_path / "before") == 0
    # The tokenizer run is retrained in place (another seed: other weights at the same step folder).
    assert main([*tiny_tokenizer_args(tok), "--overwrite", "--set", "seed=7"]) == 0
    capsys.readouterr()
    assert generate(gen, tmp_path / "after") == 2
    line = one_error_line(capsys)
    assert line.startswith(f"{gen}: its generator was trained on the tokenizer in {tok}/checkpoints/step-")
    assert line.endswith(
        "which has changed since (retrained or replaced); train the generator again on it, or restore that tokenizer"
    )
    assert not (tmp_path / "after").exists()
    # Another codebook size is refused the same way (it once ended in a traceback about code ranges).
    assert main([*tiny_tokenizer_args(tok), "--overwrite", "--set", "tokenizer.quantizer.codebook_size=16"]) == 0
    capsys.readouterr()
    assert generate(gen, tmp_path / "after") == 2
    assert "which has changed since" in one_error_line(capsys)


# -- 3. NaN weights ---------------------------------------------------------------------------------


@pytest.fixture
def nan_generator(trained, tmp_path):
    """A copy of GEN whose generator weights are NaN."""
    _, gen = trained
    copy = Path(shutil.copytree(gen, tmp_path / "gen"))
    folder = sorted((copy / "checkpoints" / "generator").glob("step-*"))[-1]
    poison(folder / "generator.safetensors")
    return copy, folder / "generator.safetensors"


def test_generate_refuses_nan_weights(nan_generator, tmp_path, capsys):
    run, poisoned = nan_generator
    assert generate(run, tmp_path / "out") == 2
    line = one_error_line(capsys)
    assert line.startswith(f"{poisoned}: ") and "hold NaN or Inf" in line and "--step" in line
    assert not (tmp_path / "out").exists()


def test_evaluate_generation_refuses_nan_weights(nan_generator, capsys):
    run, poisoned = nan_generator
    assert main(["--no-progress", "evaluate", "generation", "--run", str(run), "--n", "2", "--steps", "2"]) == 2
    assert one_error_line(capsys).startswith(f"{poisoned}: ")


def test_export_refuses_nan_weights_and_leaves_no_partial_bundle(nan_generator, tmp_path, capsys):
    run, poisoned = nan_generator
    root = tmp_path / "bundles"
    for precision in ("fp16", "fp32"):
        assert (
            main(
                [
                    "pretrained",
                    "export",
                    "--run",
                    str(run),
                    "--name",
                    "poisoned",
                    "--root",
                    str(root),
                    "--precision",
                    precision,
                ]
            )
            == 2
        )
        assert one_error_line(capsys).startswith(f"{poisoned}: ")
        assert not (root / "poisoned").exists()

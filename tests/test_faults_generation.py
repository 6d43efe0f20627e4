"""Fault injection on the generation commands: no command destroys what it reads, a generator
keeps the tokenizer it was trained on, NaN weights are refused in one line, ``generate --out`` is a
protected output.  Each case here once lost data or wrote a silently wrong result."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch
from generator_runs import tiny_tokenizer_args, train_args
from safetensors import safe_open
from safetensors.torch import save_file

from cli_checks import one_error_line, snapshot

from vqtouch.plugins.cli.app import main
from vqtouch.plugins.runtime.outputs import MARKER_NAME


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
        f"--out {tok} is --tokenizer {tok}; a command never writes into what it reads: choose another --out"
    )
    assert snapshot(tok) == before


def test_train_generator_refuses_an_out_that_holds_its_tokenizer(trained, tmp_path, capsys):
    tok, _ = trained
    parent = tmp_path / "parent"
    inside = Path(shutil.copytree(tok, parent / "tok"))
    before = snapshot(parent)
    assert main([*train_args(parent, flags=("--tokenizer", str(inside), "--overwrite"))]) == 2
    assert f"holds --tokenizer {inside}; a command never writes into what it reads: choose" in one_error_line(capsys)
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


# -- 4. generate --out is a protected output ---------------------------------------------------------


def test_generate_refuses_a_folder_that_holds_files_and_replaces_it_whole_with_overwrite(trained, tmp_path, capsys):
    _, gen = trained
    out = tmp_path / "samples"
    assert generate(gen, out, "--n", "4") == 0
    assert sorted(path.name for path in out.glob("sample_*.png")) == [f"sample_{i:04d}.png" for i in range(4)]
    before = snapshot(out)
    capsys.readouterr()
    assert generate(gen, out) == 2  # two samples into a folder holding four: once they mixed
    assert one_error_line(capsys) == (
        f"--out {out} already holds files; choose another --out, or pass --overwrite to replace them"
    )
    assert snapshot(out) == before
    assert generate(gen, out, "--overwrite") == 0
    assert sorted(path.name for path in out.iterdir()) == [
        MARKER_NAME,
        "generate.json",
        "grid.png",
        "sample_0000.png",
        "sample_0001.png",
    ]
    assert json.loads((out / "generate.json").read_text())["n"] == 2
    assert not [path for path in tmp_path.iterdir() if path.name.startswith(".")]  # no staged folder left


def test_generate_never_writes_into_its_run(trained, capsys):
    _, gen = trained
    before = snapshot(gen)
    assert generate(gen, gen, "--overwrite") == 2
    assert one_error_line(capsys) == (
        f"--out {gen} is --run {gen}; a command never writes into what it reads: choose another --out"
    )
    assert snapshot(gen) == before


def test_an_interrupted_generate_leaves_nothing_half_written(trained, tmp_path, monkeypatch):
    """Stopped after the first sample (as by Ctrl-C or SIGTERM): no --out folder, no staged leftovers."""
    import vqtouch.plugins.generator.command_handlers as handlers

    _, gen = trained
    written = []

    def stop_after_one(image, path):
        if written:
            raise KeyboardInterrupt
        written.append(path)
        return original(image, path)

    original = handlers.save_png
    monkeypatch.setattr(handlers, "save_png", stop_after_one)
    assert generate(gen, tmp_path / "out", "--n", "3") == 130
    assert written and not (tmp_path / "out").exists()
    assert list(tmp_path.iterdir()) == []


# -- 5. a huge --n ------------------------------------------------------------------------------------


def test_generate_refuses_more_samples_than_the_disk_holds(trained, tmp_path, capsys):
    _, gen = trained
    assert generate(gen, tmp_path / "out", "--n", "1000000000000") == 2
    line = one_error_line(capsys)
    assert line.startswith("--n 1000000000000: the samples need up to ") and "GB are free where --out" in line
    assert not (tmp_path / "out").exists()


def test_generate_streams_batches_and_keeps_the_images_of_one_call(trained, tmp_path):
    """Batch by batch, the samples are those of one call to the pipeline (an image depends on its
    index and the seed only), and grid.png draws at most the first 64."""
    import numpy as np
    from PIL import Image

    from vqtouch.plugins.generator import load_pipeline

    _, gen = trained
    assert generate(gen, tmp_path / "out", "--n", "5", "--batch-size", "2") == 0
    expected = load_pipeline(gen, device="cpu")(5, label="0", steps=2, seed=0, batch_size=5)
    for index in range(5):
        saved = torch.from_numpy(np.array(Image.open(tmp_path / "out" / f"sample_{index:04d}.png"))).permute(2, 0, 1)
        assert torch.equal(saved, (expected[index].clamp(0, 1) * 255).round().to(torch.uint8))


# -- 15. a full disk names the file ---------------------------------------------------------------------


def test_a_full_disk_during_generate_names_the_file(trained, tmp_path, monkeypatch, capsys):
    import errno

    from PIL import Image

    _, gen = trained

    def full_disk(self, fp, *args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Image.Image, "save", full_disk)
    assert generate(gen, tmp_path / "out") == 2
    line = one_error_line(capsys)
    assert line.startswith(str(tmp_path)) and "sample_0000.png: No space left on device; the disk is full" in line
    assert not (tmp_path / "out").exists()


# -- 16. a read-only run ------------------------------------------------------------------------------


@pytest.fixture
def read_only(monkeypatch):
    """``read_only(path)``: ``path`` reports itself not writable (root, which runs the tests here and in
    CI, may write into a mode-555 folder, so the check is what is exercised)."""
    import os

    original = os.access
    frozen: list[str] = []

    def access(path, mode, *args, **kwargs):
        if mode & os.W_OK and str(Path(path).resolve()) in frozen:
            return False
        return original(path, mode, *args, **kwargs)

    monkeypatch.setattr(os, "access", access)
    return lambda path: frozen.append(str(Path(path).resolve()))


def test_evaluate_generation_of_a_read_only_run_asks_for_out_before_sampling(trained, tmp_path, read_only, capsys):
    _, gen = trained
    read_only(gen)
    before = snapshot(gen)
    argv = ["--no-progress", "evaluate", "generation", "--run", str(gen), "--n", "2", "--steps", "2"]
    assert main(argv) == 2
    assert one_error_line(capsys) == f"--run {gen} is read-only; give --out DIR for the scores and sample pictures"
    assert main([*argv, "--out", str(tmp_path / "scores")]) == 0
    assert (tmp_path / "scores" / "generation.json").is_file() and snapshot(gen) == before


def test_evaluate_reconstruction_of_a_read_only_run_prints_its_scores(trained, read_only, capsys):
    tok, _ = trained
    read_only(tok)
    before = snapshot(tok)
    assert main(["--no-progress", "evaluate", "reconstruction", "--run", str(tok)]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)["psnr"] > 0
    assert f"{tok} is read-only: the scores above were printed, not saved" in captured.err
    assert snapshot(tok) == before


def test_report_of_a_read_only_run_writes_where_asked(tmp_path, read_only, capsys):
    import importlib.util

    spec = importlib.util.spec_from_file_location("report_runs", Path(__file__).with_name("report_runs.py"))
    report_runs = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(report_runs)
    run = report_runs.synthetic_run(tmp_path / "demo")
    read_only(run)
    before = snapshot(run)
    assert main(["report", str(run)]) == 2
    assert one_error_line(capsys) == f"{run} is read-only; give --out DIR for report.html and report.md"
    assert main(["report", str(run), "--out", str(tmp_path / "elsewhere")]) == 0
    assert "<html" in (tmp_path / "elsewhere" / "report.html").read_text()
    assert (tmp_path / "elsewhere" / "report.md").is_file() and snapshot(run) == before


def test_a_concurrent_generate_keeps_both_outputs(trained, tmp_path, monkeypatch, capsys):
    """Another process fills --out while this one samples: once they interleaved their samples; now the
    first to finish owns the folder and the other keeps its samples where it staged them, and says where."""
    import vqtouch.plugins.generator.command_handlers as handlers

    _, gen = trained
    out = tmp_path / "out"
    original = handlers.save_png

    def other_process_finishes_first(image, path):
        if not out.exists():
            out.mkdir()
            (out / "sample_0000.png").write_bytes(b"the other call's sample")
        return original(image, path)

    monkeypatch.setattr(handlers, "save_png", other_process_finishes_first)
    assert generate(gen, out) == 2
    line = one_error_line(capsys)
    assert line.startswith(f"--out {out} was filled by another process meanwhile; this command's output is in ")
    staged = Path(line.rsplit(" is in ", 1)[1])
    assert sorted(path.name for path in staged.iterdir()) == [
        MARKER_NAME,
        "generate.json",
        "grid.png",
        "sample_0000.png",
        "sample_0001.png",
    ]
    assert (out / "sample_0000.png").read_bytes() == b"the other call's sample" and len(list(out.iterdir())) == 1


def test_sigterm_during_generate_exits_143_and_leaves_nothing(trained, tmp_path, monkeypatch, capsys):
    import os
    import signal

    import vqtouch.plugins.generator.command_handlers as handlers

    _, gen = trained
    original = handlers.save_png

    def terminated_after_one(image, path):
        result = original(image, path)
        os.kill(os.getpid(), signal.SIGTERM)
        return result

    monkeypatch.setattr(handlers, "save_png", terminated_after_one)
    assert generate(gen, tmp_path / "out", "--n", "3") == 143
    assert "vqtouch: terminated (SIGTERM)" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []

"""Fault injection on the training commands' runs: a run knows its kind, and
SIGTERM before training starts is an interruption like Ctrl-C, with a resumable run."""

from __future__ import annotations

import os
import signal

import pytest
from generator_runs import tiny_tokenizer_args, train_args

from cli_checks import one_error_line, snapshot

from vqtouch.plugins.cli.app import main


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A tiny tokenizer run TOK (stages tokenizer, reconstruct) and a generator run GEN trained on it
    (stage generator)."""
    root = tmp_path_factory.mktemp("kinds")
    tok, gen = root / "tok", root / "gen"
    assert main(tiny_tokenizer_args(tok)) == 0
    assert main(train_args(gen, flags=("--tokenizer", str(tok)))) == 0
    return tok, gen


def test_train_tokenizer_refuses_to_resume_a_generator_run(runs, capsys):
    _, gen = runs
    before = snapshot(gen)
    capsys.readouterr()
    assert main(["--no-progress", "train", "tokenizer", "--resume", str(gen)]) == 2
    assert one_error_line(capsys) == (
        f"--resume {gen}: this run has no tokenizer stage (its stages: generator); resume a tokenizer run, "
        "or start one with --out"
    )
    assert snapshot(gen) == before  # once it trained a new tokenizer in it from step 0


def test_train_generator_refuses_to_resume_a_tokenizer_run(runs, capsys):
    tok, _ = runs
    before = snapshot(tok)
    capsys.readouterr()
    assert main(["--no-progress", "train", "generator", "--resume", str(tok)]) == 2
    assert "this run has no generator stage (its stages: tokenizer, reconstruct)" in one_error_line(capsys)
    assert snapshot(tok) == before  # once it wrote real_frames.png into it, then failed


def _sigterm_when_called(monkeypatch, target, name):
    original = getattr(target, name)

    def send(*args, **kwargs):
        monkeypatch.setattr(target, name, original)
        os.kill(os.getpid(), signal.SIGTERM)
        return original(*args, **kwargs)

    monkeypatch.setattr(target, name, send)


def test_sigterm_during_setup_says_so_exits_143_and_the_run_resumes(tmp_path, monkeypatch, capsys):
    """SIGTERM while the run is being created (its config written, its env.json not yet): once a silent
    exit 143 and a run that, resumed, never got its env.json."""
    import vqtouch.plugins.runtime.run_dir as runs_module

    out = tmp_path / "run"
    _sigterm_when_called(monkeypatch, runs_module, "environment_record")
    assert main(tiny_tokenizer_args(out)) == 143
    assert "vqtouch: terminated (SIGTERM)" in capsys.readouterr().err
    assert (out / "config.json").is_file() and not (out / "env.json").exists()
    assert main(["--no-progress", "train", "tokenizer", "--resume", str(out)]) == 0
    assert (out / "env.json").is_file() and (out / "eval.json").is_file()


def test_sigterm_before_the_first_step_names_what_to_do(tmp_path, monkeypatch, capsys):
    from vqtouch.core.assembly import Assembly

    out = tmp_path / "run"
    _sigterm_when_called(monkeypatch, Assembly, "component")
    assert main(tiny_tokenizer_args(out)) == 143
    err = capsys.readouterr().err
    assert (
        f"interrupted before any checkpoint was written; nothing to resume: start again with --overwrite --out {out}"
        in err
    )
    assert main([*tiny_tokenizer_args(out), "--overwrite"]) == 0

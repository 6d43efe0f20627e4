"""Finished results are never replaced without ``--overwrite``: every command that writes a result file
into its ``--out`` declares it (``add_overwrite_argument``), and the command line refuses a second call."""

from __future__ import annotations

import json

import pytest
import torch

import generator_runs
from cli_checks import leaf_commands, one_error_line, snapshot

from vqtouch.core import load_plugins
from vqtouch.plugins.cli.app import build_parser, main
from vqtouch.plugins.utils.images import save_png


@pytest.fixture(scope="module")
def tokenizer_folder(tmp_path_factory):
    return generator_runs.tiny_tokenizer_folder(tmp_path_factory.mktemp("tok"))


def test_every_command_that_writes_into_out_can_be_told_to_overwrite():
    """A command with --out and no --overwrite could only ever replace what it wrote before in silence."""
    lacking = [
        " ".join(words)
        for words, parser in leaf_commands(build_parser(load_plugins()))
        if {"out"} <= {action.dest for action in parser._actions}
        and "overwrite" not in {action.dest for action in parser._actions}
    ]
    assert lacking == ["report"]  # rebuilds the page of its run from report.json: nothing else is lost


def test_a_second_reconstruct_into_the_same_out_is_refused_unless_overwrite(tokenizer_folder, tmp_path, capsys):
    frames = tmp_path / "frames"
    frames.mkdir()
    for index in range(3):
        save_png(torch.rand(3, 32, 32, generator=torch.Generator().manual_seed(index)), frames / f"{index}.png")
    out = tmp_path / "out"
    reconstruct = ["reconstruct", "--run", str(tokenizer_folder), "--images", str(frames), "--out", str(out)]
    assert main(reconstruct) == 0
    before = snapshot(out)
    assert main(reconstruct) == 2
    assert one_error_line(capsys) == (
        f"--out {out} already holds reconstruct.json; pass --overwrite to replace it, or choose another --out"
    )
    assert snapshot(out) == before
    assert main([*reconstruct, "--overwrite"]) == 0
    assert json.loads((out / "reconstruct.json").read_text())["images"] == 3


def test_a_second_cluster_into_the_same_families_is_refused(family_tokenizer_run, tmp_path, capsys):
    out = tmp_path / "families"
    args = generator_runs.cluster_args(family_tokenizer_run, out, ["gelsight", "digit"])
    assert main(args) == 0
    before = snapshot(out)
    assert main(args) == 2
    assert "already holds cluster.json; pass --overwrite" in one_error_line(capsys)
    assert snapshot(out) == before


def test_evaluate_pairs_keeps_the_json_file_it_wrote(tmp_path, capsys):
    generated, real = tmp_path / "generated", tmp_path / "real"
    for folder in (generated, real):
        folder.mkdir()
        for index in range(2):
            save_png(torch.rand(3, 16, 16, generator=torch.Generator().manual_seed(index)), folder / f"{index}.png")
    result = tmp_path / "pairs.json"
    result.write_text("an earlier result\n")
    assert main(["evaluate", "pairs", "--generated", str(generated), "--real", str(real), "--out", str(result)]) == 2
    assert one_error_line(capsys).startswith(f"--out {result} already holds pairs.json; pass --overwrite")
    assert result.read_text() == "an earlier result\n"

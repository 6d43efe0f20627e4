"""Fault injection on ``cluster`` and ``adapt`` and on run folders."""

from __future__ import annotations

import json
import os
import shutil

import generator_runs
import pytest
import torch

from cli_checks import one_error_line

from vqtouch.plugins.cli.app import main


def _variant(name: str, seed: int, **variant) -> str:
    return json.dumps({"name": name, "variant": {"seed": seed, **variant}})


SENSORS = ["gelsight", _variant("gelsight", 1, colour_gain=[1.05, 0.95, 0.95]), "digit", _variant("digit", 2)]


@pytest.fixture(scope="module")
def tokenizer_folder(tmp_path_factory):
    return generator_runs.tiny_tokenizer_folder(tmp_path_factory.mktemp("tok"))


def cluster(run: str, out: str, *sensors: str) -> int:
    return main(["cluster", "--run", run, "--image-size", "32", "--images", "8", "--out", out, "--sensors", *sensors])


def test_cluster_refuses_a_sensor_listed_twice(tokenizer_folder, tmp_path, capsys):
    """Case 13: two identical sensors once gave threshold 0, so every later adapt was refused."""
    assert cluster(str(tokenizer_folder), str(tmp_path / "fam"), "gelsight", "gelsight", "digit") == 2
    assert one_error_line(capsys).startswith("sensor gelsight is listed 2 times: identical sensors give identical")
    assert not (tmp_path / "fam").exists()


def test_families_are_recognised_from_another_directory_and_after_the_tokenizer_moves(
    tokenizer_folder, tmp_path, monkeypatch, capsys
):
    """Case 17: cluster.json once stored the tokenizer path as typed (relative), so ``adapt --families``
    from another directory refused the very tokenizer the families were fitted on."""
    here = tmp_path / "here"
    here.mkdir()
    monkeypatch.chdir(here)
    assert cluster(os.path.relpath(tokenizer_folder, here), "fam", *SENSORS) == 0
    recorded = json.loads((here / "fam" / "cluster.json").read_text())
    assert recorded["tokenizer"] == str(tokenizer_folder.resolve()) and len(recorded["tokenizer_sha256"]) == 64
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    moved = shutil.copytree(tokenizer_folder, tmp_path / "moved_tokenizer")
    target = _variant("gelsight", 7, illumination_shift=0.04)
    common = [
        "--images",
        target,
        "--shots",
        "4",
        "--ratio",
        "2",
        "--steps",
        "1",
        "--eval-images",
        "4",
        "--batch-size",
        "4",
        "--threshold",
        "1",
    ]
    for tokenizer in (tokenizer_folder, moved):
        assert (
            main(
                [
                    "adapt",
                    "--run",
                    str(tokenizer),
                    "--families",
                    str(here / "fam"),
                    "--out",
                    f"adapted_{tokenizer.name}",
                    *common,
                ]
            )
            == 0
        ), capsys.readouterr().err
    # A tokenizer whose weights differ is still refused.
    from safetensors import safe_open
    from safetensors.torch import load_file, save_file

    capsys.readouterr()
    changed = tmp_path / "changed"
    shutil.copytree(tokenizer_folder, changed)
    with safe_open(str(changed / "autoencoder.safetensors"), framework="pt") as handle:
        header = handle.metadata()
    tensors = load_file(str(changed / "autoencoder.safetensors"))
    first = next(iter(tensors))
    tensors[first] = tensors[first] + 1
    save_file(tensors, str(changed / "autoencoder.safetensors"), metadata=header)
    assert main(["adapt", "--run", str(changed), "--families", str(here / "fam"), "--out", "refused", *common]) == 2
    assert "were fitted on the features of" in one_error_line(capsys)


def test_a_run_folder_without_its_config_is_described_the_same_way_twice(tmp_path, capsys):
    """Case 18: once "continue it with --resume", and --resume then "not a run directory"."""
    out = tmp_path / "run"
    assert main(generator_runs.tiny_tokenizer_args(out)) == 0
    (out / "config.json").unlink()
    capsys.readouterr()
    assert main(generator_runs.tiny_tokenizer_args(out)) == 2
    first = one_error_line(capsys)
    assert first == (
        f"{out} holds a run without its config.json (stopped while it was being created, or the file "
        "was deleted), which cannot be resumed; start it afresh with --overwrite, or choose another --out"
    )
    assert main(["--no-progress", "train", "tokenizer", "--resume", str(out)]) == 2
    assert "which cannot be resumed; start it afresh with --overwrite --out" in one_error_line(capsys)
    assert main([*generator_runs.tiny_tokenizer_args(out), "--overwrite"]) == 0


def _greyscale_folder(folder, count=4, size=32):
    from PIL import Image

    folder.mkdir(parents=True)
    generator = torch.Generator().manual_seed(0)
    for index in range(count):
        pixels = (torch.rand(size, size, generator=generator) * 255).to(torch.uint8).numpy()
        Image.fromarray(pixels, mode="L").save(folder / f"frame_{index}.png")
    return folder


def test_greyscale_images_can_be_allowed_where_the_message_says(tokenizer_folder, tmp_path, capsys):
    """Case 14: the error said "set allow_greyscale=true", which cluster, adapt, generate --visual and
    evaluate pairs had no way to set."""
    grey = _greyscale_folder(tmp_path / "grey")
    assert cluster(str(tokenizer_folder), str(tmp_path / "fam"), str(grey), "gelsight", "digit") == 2
    line = one_error_line(capsys)
    assert "is greyscale (mode L); to copy it into 3 channels pass --allow-greyscale" in line
    argv = [
        "cluster",
        "--run",
        str(tokenizer_folder),
        "--image-size",
        "32",
        "--images",
        "4",
        "--out",
        str(tmp_path / "fam"),
        "--allow-greyscale",
        "--sensors",
        str(grey),
        "gelsight",
        "digit",
    ]
    assert main(argv) == 0
    pairs = ["evaluate", "pairs", "--generated", str(grey), "--real", str(grey), "--protocol", "default"]
    assert main(pairs) == 2
    assert "pass --allow-greyscale" in one_error_line(capsys)
    assert main([*pairs, "--allow-greyscale"]) == 0
    for command in ("adapt", "generate"):
        assert main([command, "--help"]) == 0
        assert "--allow-greyscale" in capsys.readouterr().out

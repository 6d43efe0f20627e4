"""The output rule (vqtouch.plugins.runtime.outputs): no command writes into, replaces or empties what it reads,
nor anything inside the installed package; ``--overwrite`` replaces only the same command's output.

The property tests walk every command's parser, so a command added later is covered without a word here.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from cli_checks import leaf_commands, one_error_line, snapshot

from vqtouch.core import ConfigError, VqtouchWarning, load_plugins
from vqtouch.plugins.cli.app import NumberType, build_parser, main
from vqtouch.plugins.runtime.outputs import (
    MARKER_NAME,
    check_output,
    clean_leftovers,
    command_inputs,
    output_folder,
    package_folders,
    reading,
    staged_output,
)

OUTPUTS = {"out", "resume"}


def _filler(action: argparse.Action) -> list[str]:
    """A value that parses for a required action (its first choice, the low end of its range)."""
    if action.choices:
        value = str(next(iter(action.choices)))
    elif isinstance(action.type, NumberType):
        value = str(int(action.type.low or 1)) if action.type.kind is int else "1"
    else:
        value = "x"
    return [value] if action.option_strings == [] else [action.option_strings[-1], value]


def _path_options(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    """The options and positionals that take free text (any of which may name a file or folder), and
    that may be given with ``--out``."""
    exclusive = {
        action.dest
        for group in parser._mutually_exclusive_groups
        if "out" in {member.dest for member in group._group_actions}
        for action in group._group_actions
    }
    return [
        action
        for action in parser._actions
        if action.dest not in OUTPUTS | exclusive
        and not action.choices
        and action.type is None
        and action.nargs != 0
        and not isinstance(action, (argparse._HelpAction, argparse._VersionAction, argparse._StoreConstAction))
        and action.dest not in ("overrides", "config")  # --set/--config: covered by their own test
    ]


def _required_groups(parser: argparse.ArgumentParser) -> list:
    """The required groups of one-of options, but the one ``--out`` belongs to (given by every case)."""
    return [
        group
        for group in parser._mutually_exclusive_groups
        if group.required and "out" not in {action.dest for action in group._group_actions}
    ]


def _argv(words, parser, path_action, path: Path, out: Path, overwrite: bool) -> list[str]:
    argv = list(words)
    given = {path_action.dest}
    for group in _required_groups(parser):
        if not any(action.dest in given for action in group._group_actions):
            argv += _filler(group._group_actions[0])
            given.add(group._group_actions[0].dest)
    for action in parser._actions:
        if action.required and action.dest not in given and action.dest != "out":
            argv += _filler(action)
    argv += [str(path)] if not path_action.option_strings else [path_action.option_strings[-1], str(path)]
    return argv + ["--out", str(out)] + (["--overwrite"] if overwrite else [])


def _cases():
    parser = build_parser(load_plugins())
    for words, command in leaf_commands(parser):
        if "out" not in {action.dest for action in command._actions}:
            continue
        overwrites = "overwrite" in {action.dest for action in command._actions}
        for action in _path_options(command):
            yield pytest.param(words, action.dest, overwrites, id=f"{' '.join(words)}:{action.dest}")


CASES = list(_cases())


def test_every_command_that_writes_is_walked():
    walked = {case.values[0] for case in CASES}
    for command in (("fewshot",), ("adapt",), ("cluster",), ("reconstruct",), ("generate",), ("report",)):
        assert command in walked
    assert ("evaluate", "mix-ratio") in walked and ("evaluate", "fewshot-generation") in walked
    assert len(CASES) > 60


def _refused_untouched(words, dest, where, overwrite, tmp_path, capsys) -> None:
    """``--out`` ``where`` (the same as, inside, containing) a folder given to option ``dest`` of the
    command ``words`` is refused in one line, with and without ``--overwrite`` when the command has it,
    and every file under the test's folder is as it was."""
    parser = build_parser(load_plugins())
    command = dict(leaf_commands(parser))[words]
    action = next(action for action in command._actions if action.dest == dest)
    folder = tmp_path / "inputs" / "read"
    (folder / "sub").mkdir(parents=True)
    (folder / "cluster.json").write_text('{"kept": true}\n')
    (folder / "sub" / "000.png").write_bytes(b"\x89PNG not really")
    before = snapshot(tmp_path)
    out = {"same": folder, "inside": folder / "sub" / "out", "containing": tmp_path / "inputs"}[where]
    for each in (False, True) if overwrite else (False,):
        assert main(_argv(words, command, action, folder, out, each)) == 2
        message = one_error_line(capsys)
        assert message.startswith(f"--out {out} ") and "a command never writes into what it reads" in message
        assert snapshot(tmp_path) == before


@pytest.mark.parametrize("words, dest, overwrites", CASES)
def test_no_command_writes_inside_any_folder_it_reads(words, dest, overwrites, tmp_path, capsys):
    """Every option of every command: --out inside what it names (with and without --overwrite, where
    the command has it)."""
    _refused_untouched(words, dest, "inside", overwrites, tmp_path, capsys)


FIRST_CASES = list({case.values[0]: case for case in reversed(CASES)}.values())


@pytest.mark.parametrize("words, dest, overwrites", FIRST_CASES)
@pytest.mark.parametrize("where", ["same", "containing"])
def test_no_command_replaces_or_empties_what_it_reads(words, dest, overwrites, where, tmp_path, capsys):
    """Every command: --out equal to what it reads, and holding it (with and without --overwrite)."""
    _refused_untouched(words, dest, where, overwrites, tmp_path, capsys)


@pytest.mark.parametrize("words", sorted({case.values[0] for case in CASES}), ids=" ".join)
def test_no_command_writes_inside_the_installed_package(words, capsys):
    parser = build_parser(load_plugins())
    command = dict(leaf_commands(parser))[words]
    bundle = package_folders()[1] / "pretrained" / "weights" / "tour"
    argv = list(words)
    for group in _required_groups(command):
        argv += _filler(group._group_actions[0])
    for action in command._actions:
        if action.required and action.dest != "out":
            argv += _filler(action)
    before = snapshot(bundle)
    for out in (bundle, bundle / "gen", package_folders()[1].parent):
        assert main([*argv, "--out", str(out)]) == 2
        assert "installed vqtouch package" in one_error_line(capsys)
    assert snapshot(bundle) == before


def test_inputs_are_found_in_json_blocks_and_settings(tmp_path):
    parser = build_parser(load_plugins())
    data = tmp_path / "data"
    data.mkdir()
    block = json.dumps({"name": "image_folder", "root": str(data)})
    args = parser.parse_args(
        ["evaluate", "reconstruction", "--dataset", block, "--set", f"data.root={data}", "--out", "o"]
    )
    command, reads = command_inputs(parser, args)
    assert command == "evaluate reconstruction"
    assert {(flag, path) for flag, _, path in reads} == {("--dataset", str(data)), ("--set", str(data))}
    # output_dir names where runs are written, not what is read
    args = parser.parse_args(["train", "tokenizer", "--set", f"output_dir={data}"])
    assert command_inputs(parser, args)[1] == []


def test_a_config_file_is_an_input(tmp_path, capsys):
    recipe = tmp_path / "recipes" / "tour.toml"
    recipe.parent.mkdir()
    recipe.write_text("[tokenizer.train]\nsteps = 1\n")
    assert main(["train", "tokenizer", "--config", str(recipe), "--out", str(recipe.parent), "--overwrite"]) == 2
    assert "holds --config" in one_error_line(capsys)
    assert recipe.is_file()


def test_library_callers_pass_what_they_read(tmp_path):
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    with pytest.raises(ConfigError, match="is inside the tokenizer run this command reads"):
        check_output(run / "checkpoints", [("--tokenizer", "tokenizer run", run)])
    with pytest.raises(ConfigError, match="holds"):
        output_folder(tmp_path, [("--run", "run", run)])
    with reading([("--images", "input", str(run))], "adapt"), pytest.raises(ConfigError, match="is --images"):
        with staged_output(run):
            pass
    check_output(tmp_path / "elsewhere", [("--run", "run", run)])  # beside an input is fine


def test_overwrite_replaces_only_the_same_commands_output(tmp_path):
    out = tmp_path / "out"
    with staged_output(out, command="generate") as folder:
        (folder / "a.png").write_bytes(b"1")
    assert json.loads((out / MARKER_NAME).read_text()) == {"command": "generate"}
    with staged_output(out, overwrite=True, command="generate") as folder:
        (folder / "b.png").write_bytes(b"2")
    assert sorted(path.name for path in out.iterdir()) == [MARKER_NAME, "b.png"]
    with pytest.raises(
        ConfigError,
        match="written by `vqtouch generate`; --overwrite only replaces an earlier output of `vqtouch fewshot`",
    ):
        with staged_output(out, overwrite=True, command="fewshot"):
            pass
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("my own notes\n")
    with pytest.raises(ConfigError, match="written by no vqtouch command"):
        with staged_output(mine, overwrite=True, command="generate"):
            pass
    assert (mine / "notes.txt").read_text() == "my own notes\n" and (out / "b.png").is_file()


def test_a_killed_calls_staging_folder_is_removed_by_the_next_call(tmp_path):
    out = tmp_path / "out"
    code = (
        "import os, sys\n"
        "from vqtouch.plugins.runtime.outputs import staged_output\n"
        f"with staged_output({str(out)!r}, command='generate') as folder:\n"
        "    (folder / 'half.png').write_bytes(b'1')\n"
        "    print(folder, flush=True)\n"
        "    os.kill(os.getpid(), 9)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == -signal.SIGKILL
    left = Path(done.stdout.strip())
    assert left.is_dir() and left.parent == tmp_path and not out.exists()
    with pytest.warns(VqtouchWarning, match="removed 1 unfinished output folder"):
        with staged_output(out, command="generate") as folder:
            assert not left.exists()
            assert clean_leftovers(out) == [] and folder.is_dir()  # a running call's folder is not a leftover
    assert os.listdir(tmp_path) == ["out"]

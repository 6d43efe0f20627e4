"""Every numeric option of every command refuses what it cannot use (NaN, infinities, out-of-range,
fractions for integers, huge seeds) in one line with exit 2, and passes on only finite, in-range
values."""

from __future__ import annotations

import argparse
import math

import pytest
from generator_runs import TINY

from vqtouch.plugins.cli.app import NumberType, build_parser, main
from vqtouch.core.plugin_manager import load_plugins

#: What a careless user types.
PROBES = [
    "nan",
    "NaN",
    "inf",
    "-inf",
    "-1",
    "0",
    "0.5",
    "1",
    "1.5",
    "1e30",
    "-1e-30",
    "99999999999999999999",
    "abc",
    "",
]


def _options(parser: argparse.ArgumentParser, prog: str = "vqtouch"):
    """(command, option, action) for every option of every (sub)command."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _options(sub, f"{prog} {name}")
        elif action.option_strings:
            yield prog, action.option_strings[-1], action


OPTIONS = list(_options(build_parser(load_plugins(autoload=False))))
NUMERIC = [(prog, flag, action) for prog, flag, action in OPTIONS if isinstance(action.type, NumberType)]


def test_no_option_takes_a_bare_int_or_float():
    """int() and float() accept NaN, infinities and negatives; every numeric option says its range."""
    bare = [f"{prog} {flag}" for prog, flag, action in OPTIONS if action.type in (int, float)]
    assert bare == []
    assert len(NUMERIC) >= 40  # the sweep below covers the commands' numeric options


@pytest.mark.parametrize(("prog", "flag", "action"), NUMERIC, ids=[f"{p} {f}" for p, f, _ in NUMERIC])
def test_every_numeric_option_is_refused_or_finite_and_in_range(prog, flag, action):
    kind = action.type
    low, high, low_open, high_open = kind.bounds
    for text in PROBES:
        try:
            value = kind(text)
        except argparse.ArgumentTypeError as exc:
            assert "\n" not in str(exc) and str(exc), (flag, text)
            continue
        assert isinstance(value, kind.kind) and math.isfinite(value), (flag, text, value)
        assert low is None or (value > low if low_open else value >= low), (flag, text, value)
        assert high is None or (value < high if high_open else value <= high), (flag, text, value)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["generate", "--guidance", "nan"], "argument --guidance: nan: must be a finite number in [0, 1000]"),
        (["generate", "--guidance=-inf"], "argument --guidance: -inf: must be a finite number in [0, 1000]"),
        (["generate", "--truncation=-0.5"], "argument --truncation: -0.5: must be a finite number in (0, 1]"),
        (["generate", "--seed", "99999999999999999999"], "argument --seed: 99999999999999999999: must be an integer"),
        (["evaluate", "generation", "--guidance", "inf"], "argument --guidance: inf: must be a finite number"),
        (["evaluate", "generation", "--seed=-3"], "argument --seed: -3: must be an integer in [0, 4294967295]"),
        (["evaluate", "downstream", "--guidance=-1"], "argument --guidance: -1: must be a finite number"),
        (["cluster", "--threshold", "nan"], "argument --threshold: nan: must be a finite number >= 0"),
        (["adapt", "--threshold", "nan"], "argument --threshold: nan: must be a finite number >= 0"),
        (["adapt", "--learning-rate", "nan"], "argument --learning-rate: nan: must be a finite number in (0, 10]"),
        (["adapt", "--learning-rate", "1e6"], "argument --learning-rate: 1e6: must be a finite number in (0, 10]"),
        (["adapt", "--seed", "99999999999999999999"], "argument --seed: 99999999999999999999: must be an integer"),
    ],
)
def test_bad_numbers_stop_the_command_in_one_line(argv, message, capsys):
    assert main(["--no-progress", *argv]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("vqtouch: error: vqtouch "), err
    assert message in err


def _error_line(capsys) -> str:
    err = capsys.readouterr().err
    assert err.startswith("vqtouch: error: ") and err.count("\n") == 1, err
    return err


def test_a_huge_seed_is_refused_with_the_config(tmp_path, capsys):
    """Case 9: it once validated, then training crashed on the overflow."""
    out = tmp_path / "run"
    argv = ["--no-progress", "train", "tokenizer", "--out", str(out), "--set", "seed=9223372036854775807"]
    assert main(argv) == 2
    assert "seed: Input should be less than or equal to 4294967295" in _error_line(capsys)
    assert not out.exists()


def test_sampling_steps_beyond_the_model_are_refused_before_training(tmp_path, capsys):
    """Case 10: ``generator.steps=200`` once validated, trained, then crashed on its own limit."""
    out = tmp_path / "run"
    tiny = [item for override in TINY for item in ("--set", override)]  # were it to train, it trains in seconds
    argv = ["--no-progress", "train", "generator", "--scene", "label-to-touch", "--out", str(out), *tiny]
    assert main([*argv, "--set", "generator.model.num_steps=100", "--set", "generator.steps=200"]) == 2
    line = _error_line(capsys)
    assert "steps=200 exceeds the generator's diffusion steps (generator.model.num_steps=100)" in line, line
    assert not out.exists()

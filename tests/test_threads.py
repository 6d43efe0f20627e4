"""Threads on a busy CPU: the default follows the free cores and drops to one
thread, saying so in one line, when the load exceeds the cores; --threads and VQTOUCH_THREADS
choose; the caller's thread count is restored after a command."""

import io

import pytest
import torch

from vqtouch.core import ConfigError
from vqtouch.plugins.cli.app import main
from vqtouch.plugins.utils.threads import busy_cpu_threads, command_threads


def test_the_default_follows_the_free_cores_and_says_when_it_drops():
    assert busy_cpu_threads(cores=2, load=0.1, wanted=2) == (2, None)  # idle: torch's default
    threads, note = busy_cpu_threads(cores=2, load=3.5, wanted=2)  # overloaded: one thread
    assert threads == 1 and note.startswith("the CPU is busy (load 3.5 on 2 cores): running on 1 thread instead of 2")
    assert "--threads N" in note
    assert busy_cpu_threads(cores=16, load=5.2, wanted=16)[0] == 11  # the cores left free
    assert busy_cpu_threads(cores=8, load=7.9, wanted=8)[0] == 1


def test_a_command_runs_on_the_chosen_threads_and_restores_the_callers(monkeypatch, capsys):
    original = torch.get_num_threads()
    torch.set_num_threads(2)  # the caller's count, whatever OMP_NUM_THREADS the suite runs under
    before = torch.get_num_threads()
    seen = []
    monkeypatch.setattr("vqtouch.plugins.cli.app._cmd_plugins", lambda args: seen.append(torch.get_num_threads()) or 0)
    assert main(["--threads", "1", "plugins"]) == 0
    monkeypatch.setenv("VQTOUCH_THREADS", "auto")
    monkeypatch.setattr("vqtouch.plugins.utils.threads.current_load", lambda: 99.0)
    assert main(["plugins"]) == 0
    assert seen == [1, 1] and torch.get_num_threads() == before
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("vqtouch: note: the CPU is busy (load 99.0 on ")
    monkeypatch.setenv("VQTOUCH_THREADS", "lots")
    assert main(["plugins"]) == 2
    assert "VQTOUCH_THREADS='lots': give a number of threads" in capsys.readouterr().err
    torch.set_num_threads(original)


def test_an_explicit_count_is_taken_as_given():
    before = torch.get_num_threads()
    with command_threads(3) as note:
        assert torch.get_num_threads() == 3 and note is None
    assert torch.get_num_threads() == before
    with pytest.raises(ConfigError):
        with command_threads("-2"):
            pass


def test_the_load_is_the_runnable_tasks_now_less_this_one(monkeypatch, tmp_path):
    from vqtouch.plugins.utils import threads as seeding

    samples = iter(["0.10 0.20 0.30 4/300 99\n", "0.10 0.20 0.30 2/300 99\n", "0.10 0.20 0.30 3/300 99\n"])
    real_open = open

    def fake_open(path, *args, **kwargs):
        return io.StringIO(next(samples)) if path == "/proc/loadavg" else real_open(path, *args, **kwargs)

    monkeypatch.setattr("builtins.open", fake_open)
    assert seeding.current_load(samples=3, interval_s=0) == 2.0  # median of 3, 1, 2


def test_threads_may_be_given_before_or_after_a_command_that_has_its_own_option():
    from vqtouch.core import load_plugins
    from vqtouch.plugins.cli.app import build_parser

    parser = build_parser(load_plugins(autoload=False))
    command = ["tradeoff", "generator", "--run", "r", "--out", "o"]
    assert parser.parse_args(["--threads", "1", *command]).threads == 1
    assert parser.parse_args([*command, "--threads", "3"]).threads == 3
    assert parser.parse_args(command).threads is None

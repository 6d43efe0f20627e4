"""Progress when output is redirected: a long loop still prints a plain line at
least every REDIRECTED_INTERVAL_S, each state on a line of its own; a short one prints nothing; on
a terminal the bar is tqdm's; --no-progress silences both."""

import io

import pytest

from vqtouch.plugins.utils import progress as progress_module
from vqtouch.plugins.utils.progress import disable_progress, progress


class FakeClock:
    def __init__(self):
        self.now = 1000.0

    def __call__(self):
        return self.now


@pytest.fixture(autouse=True)
def progress_on(monkeypatch):
    monkeypatch.delenv("VQTOUCH_NO_PROGRESS", raising=False)  # the suite turns bars off everywhere else
    monkeypatch.setattr(progress_module, "_forced_off", False)  # an earlier `--no-progress` command's switch


@pytest.fixture
def clock(monkeypatch):
    fake = FakeClock()
    monkeypatch.setattr("tqdm.std.time", fake)  # tqdm reads its clock from here
    return fake


def test_a_redirected_long_loop_prints_a_line_every_interval_and_a_short_one_nothing(clock):
    log = io.StringIO()
    for _ in progress(range(3), desc="short", unit="step", stream=log):
        clock.now += 1.0  # 3 s in all: under the first 30 s
    assert log.getvalue() == ""

    log = io.StringIO()
    for _ in progress(range(10), desc="training", unit="step", stream=log):
        clock.now += 10.0  # 100 s in all
    lines = log.getvalue().splitlines()
    assert "\r" not in log.getvalue() and all(line.startswith("training:") for line in lines)
    # After 30 s, then at most one line per 30 s, and the final state when the bar closes.
    assert 3 <= len(lines) <= 5 and "10/10" in lines[-1]


def test_no_progress_silences_the_redirected_lines(clock):
    log = io.StringIO()
    disable_progress()
    try:
        for _ in progress(range(10), desc="training", stream=log):
            clock.now += 10.0
    finally:
        disable_progress(False)
    assert log.getvalue() == ""


def test_a_terminal_gets_the_redrawn_bar():
    class Terminal(io.StringIO):
        def isatty(self):
            return True

    screen = Terminal()
    for _ in progress(range(3), desc="bar", stream=screen):
        pass
    assert "\r" in screen.getvalue() and "3/3" in screen.getvalue()
    assert progress_module.REDIRECTED_INTERVAL_S == 30.0


def test_no_progress_on_one_command_does_not_outlive_it(monkeypatch):
    from vqtouch.plugins.cli.app import main
    from vqtouch.plugins.utils.progress import progress_forced_off

    monkeypatch.setattr("vqtouch.plugins.cli.app._cmd_plugins", lambda args: 0 if progress_forced_off() else 1)
    assert main(["--no-progress", "plugins"]) == 0  # off while it ran
    assert progress_forced_off() is False

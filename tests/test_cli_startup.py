"""The command line starts without importing torch: help, configs and the plugin list load every plugin
(each entry point is imported at start-up), so every plugin module must stay light and name its heavy
implementation by reference.  bench/bench_cli_startup.py measures the time and memory this saves."""

from __future__ import annotations

import json
import subprocess
import sys

#: Packages a command that only prints must not import (each costs start-up time and memory).
HEAVY = ("torch", "torchvision", "numpy", "safetensors", "sklearn", "open_clip", "PIL")

#: The child: every printing command in one interpreter, in order; the first after which a heavy package
#: is in sys.modules is reported (a fresh interpreter per command would take a minute).
CHILD = """
import argparse, contextlib, io, json, sys
from vqtouch.core import load_plugins
from vqtouch.plugins.cli.app import build_parser, main

HEAVY = json.loads(sys.argv[1])


def help_paths(parser, prefix=()):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield [*prefix, name, "--help"]
                yield from help_paths(sub, (*prefix, name))


commands = [["--help"], *help_paths(build_parser(load_plugins()))]
commands += [["config", "scenes"], ["config", "stages"], ["config", "show", "tour"], ["plugins"], ["plugins", "--json"]]
report = {"count": len(commands), "codes": {}, "first_heavy": None}
for argv in commands:
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        try:
            code = main(argv)
        except SystemExit as stop:
            code = stop.code
    report["codes"][" ".join(argv)] = code
    heavy = [name for name in HEAVY if name in sys.modules]
    if heavy:
        report["first_heavy"] = [" ".join(argv), heavy]
        break
print(json.dumps(report))
"""


def test_help_configs_and_plugins_import_no_torch():
    done = subprocess.run(
        [sys.executable, "-c", CHILD, json.dumps(HEAVY)], capture_output=True, text=True, check=True, timeout=300
    )
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert report["first_heavy"] is None, f"`vqtouch {report['first_heavy'][0]}` imported {report['first_heavy'][1]}"
    assert report["count"] > 40  # every subcommand's help was run, not just the top level
    assert set(report["codes"].values()) == {0}, {argv: code for argv, code in report["codes"].items() if code}

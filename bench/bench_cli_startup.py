"""How fast the command line starts: wall time, peak memory and whether torch was imported, for the
commands that only print (help, configs, the plugin list), each in a fresh interpreter.

Run:  .venv/bin/python bench/bench_cli_startup.py [--repeats 5]

Each command runs ``--repeats`` times in a new process (``python -c`` calling ``vqtouch.plugins.cli.app.main``,
what the ``vqtouch`` script does); reported: the median wall time, the largest peak resident memory
(the child's own ``ru_maxrss``) and whether ``torch`` was in ``sys.modules`` when the command returned.
Run it on an idle machine: start-up time is mostly imports, which a busy CPU stretches.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time

COMMANDS = (
    ["--help"],
    ["train", "--help"],
    ["train", "generator", "--help"],
    ["config", "scenes"],
    ["config", "show", "tour"],
    ["plugins"],
)

#: The child: run the command, then say whether torch came in (stdout is the command's own).
CHILD = """
import contextlib, io, json, resource, sys
from vqtouch.plugins.cli.app import main
with contextlib.redirect_stdout(io.StringIO()):
    try:
        code = main(json.loads(sys.argv[1]))
    except SystemExit as stop:
        code = stop.code
peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps({"code": code, "torch": "torch" in sys.modules, "peak_mb": peak_mb}))
"""


def run_once(argv: list[str]) -> tuple[float, dict]:
    """Seconds and the child's report (exit code, torch imported, peak resident MB) of one run."""
    tic = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", CHILD, json.dumps(argv)], capture_output=True, text=True, check=True)
    return time.perf_counter() - tic, json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    print("| command | median s | peak MB | imports torch |\n|---|---|---|---|")
    for argv in COMMANDS:
        runs = [run_once(argv) for _ in range(args.repeats)]
        seconds = statistics.median(run[0] for run in runs)
        peak_mb = max(report["peak_mb"] for _, report in runs)
        print(f"| `vqtouch {' '.join(argv)}` | {seconds:.2f} | {peak_mb:.0f} | {runs[-1][1]['torch']} |")


if __name__ == "__main__":
    main()

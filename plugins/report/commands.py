"""``vqtouch demo`` and ``vqtouch report``: the quick start's command and the report's rebuild."""

from __future__ import annotations

from vqtouch.core import hookimpl
from vqtouch.plugins.cli.app import add_config_arguments


@hookimpl
def vqtouch_add_commands(subparsers):
    demo = subparsers.add_parser("demo", help="run a scene end to end on the embedded data and write a report")
    add_config_arguments(demo, default_scene="tour")
    demo.add_argument("--out", help="run directory (default: <output_dir>/<name>-<time>-<hash>)")
    demo.add_argument(
        "--overwrite",
        action="store_true",
        help="empty the --out run directory first (refused for a folder that holds no run)",
    )
    demo.add_argument(
        "--full",
        action="store_true",
        help="run the scene at its configured size (default: scaled down to minutes on a CPU)",
    )
    demo.set_defaults(handler="vqtouch.plugins.report.command_handlers:cmd_demo")

    report = subparsers.add_parser(
        "report", help="rebuild report.html and report.md of a demo run from its report.json"
    )
    report.add_argument("run_dir", metavar="RUN_DIR", help="the folder of a `vqtouch demo` run (its --out)")
    report.add_argument("--out", help="write report.html and report.md here instead (e.g. for a read-only run)")
    report.set_defaults(handler="vqtouch.plugins.report.command_handlers:cmd_report")

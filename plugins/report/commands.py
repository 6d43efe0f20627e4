"""``vqtouch demo`` and ``vqtouch report``: the quick start's command and the report's rebuild."""

from __future__ import annotations

import argparse

from vqtouch.core import RunDir, hookimpl
from vqtouch.core.cli import add_config_arguments, config_from_args


def _demo_command(args: argparse.Namespace) -> int:
    from .demo import run_demo, scale_for_demo

    host = args.host
    config = config_from_args(args, host)
    if not args.full:
        config = scale_for_demo(config, host)
    if "generator" in config.stages:
        from vqtouch.plugins.generator import check_condition_keys

        check_condition_keys(config, host)  # before the run folder exists and the tokenizer trains
    run = RunDir.create(config, argv=args.argv, host=host, path=args.out, overwrite=args.overwrite)
    with run:  # releases the run's lock however the demo ends
        report = run_demo(config, host, run)
    print(f"report: {run.path / 'report.html'}")
    ran = sum(stage["status"].startswith("ran") for stage in report["stages"])
    blocked = sum(stage["status"].startswith("cannot run") for stage in report["stages"])
    failed = sum(stage["status"].startswith("failed") for stage in report["stages"])
    print(
        f"scene {config.scene}: {ran} of {len(report['stages'])} stages ran, {blocked} cannot run, {failed} failed "
        "(reasons in the report)"
    )
    return 0


def _report_command(args: argparse.Namespace) -> int:
    from .demo import rebuild_report

    print(f"report: {rebuild_report(args.run_dir, out=args.out)}")
    return 0


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
    demo.set_defaults(handler=_demo_command)

    report = subparsers.add_parser(
        "report", help="rebuild report.html and report.md of a demo run from its report.json"
    )
    report.add_argument("run_dir", metavar="RUN_DIR", help="the folder of a `vqtouch demo` run (its --out)")
    report.add_argument("--out", help="write report.html and report.md here instead (e.g. for a read-only run)")
    report.set_defaults(handler=_report_command)

"""``vqtouch demo`` and ``vqtouch report``: the handlers (their parsers are in commands.py)."""

from __future__ import annotations

import argparse

from vqtouch.plugins.runtime.run_dir import RunDir
from vqtouch.plugins.cli.app import config_from_args


def cmd_demo(args: argparse.Namespace) -> int:
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


def cmd_report(args: argparse.Namespace) -> int:
    from .demo import rebuild_report

    print(f"report: {rebuild_report(args.run_dir, out=args.out)}")
    return 0

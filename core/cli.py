"""The ``vqtouch`` command line.

``main(argv) -> int`` builds an argparse parser whose subcommands come from core
(``plugins``, ``config``, ``demo``) and from plugins (``vqtouch_add_commands``).  User
errors print one line, ``vqtouch: error: ...``, and exit with status 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from typing import Any

from .config import resolve_config
from .errors import ConfigError, VqtouchError
from .plugin_manager import PluginHost, load_plugins
from .progress import disable_progress
from .stages import StageOutcome, empty_slot_reason, missing_slots


def add_config_arguments(parser: argparse.ArgumentParser, *, scene_required: bool = False,
                         default_scene: str | None = None) -> None:
    """Add ``SCENE``/``--scene``, ``--config`` and ``--set`` to a subcommand (for plugin commands too)."""
    if scene_required:
        parser.add_argument("scene_positional", nargs="?", metavar="SCENE",
                            help="scene preset name (see `vqtouch config scenes`)")
        parser.add_argument("--scene", help="the scene as an option, as the other commands take it")
        parser.set_defaults(scene_required=True)
    else:
        parser.add_argument("--scene", default=default_scene, help=f"scene preset (default: {default_scene})")
    parser.add_argument("--config", action="append", default=[], metavar="FILE",
                        help="TOML or JSON config merged over the scene (repeatable, in order)")
    parser.add_argument("--set", action="append", default=[], dest="overrides", metavar="PATH=VALUE",
                        help="override one value, e.g. --set tokenizer.train.steps=200 (JSON values; repeatable)")


def command_group(subparsers: argparse._SubParsersAction, name: str, help: str) -> argparse._SubParsersAction:
    """The sub-commands of group ``name`` (``train``, ``evaluate``, ...), created on first use.

    Several plugins add actions to one group: ``vqtouch train tokenizer`` and ``vqtouch train
    generator`` come from different plugins.
    """
    groups = subparsers.__dict__.setdefault("_vqtouch_groups", {})
    if name not in groups:
        parser = subparsers.add_parser(name, help=help)
        groups[name] = parser.add_subparsers(dest=f"{name}_command", metavar="WHAT", required=True)
    return groups[name]


def config_from_args(args: argparse.Namespace, host: PluginHost) -> Any:
    """Resolve the experiment config from parsed ``SCENE/--scene/--config/--set`` arguments.

    Command handlers get the command's plugin host as ``args.host``.
    """
    scene, positional = args.scene, getattr(args, "scene_positional", None)
    if positional and scene and positional != scene:
        raise ConfigError(f"two different scenes given: {positional!r} and --scene {scene!r}; give one")
    scene = positional or scene
    if getattr(args, "scene_required", False) and not scene:
        raise ConfigError("name a scene, e.g. `vqtouch config show reconstruction` (list: `vqtouch config scenes`)")
    return resolve_config(scene, args.config, args.overrides, host=host)


def _cmd_plugins(args: argparse.Namespace) -> int:
    host = args.host
    rows = host.describe()
    if args.kind:
        rows = [row for row in rows if row["kind"] == args.kind]
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    headers = ("kind", "name", "plugin", "package", "version", "description")
    widths = [max(len(h), *(len(str(row[h] or "-")) for row in rows)) if rows else len(h) for h in headers[:-1]]
    print("  ".join(h.upper().ljust(w) for h, w in zip(headers[:-1], widths)) + "  DESCRIPTION")
    for row in rows:
        cells = [str(row[h] or "-").ljust(w) for h, w in zip(headers[:-1], widths)]
        print("  ".join(cells) + "  " + row["description"])
    return 0


def _cmd_config_show(args: argparse.Namespace) -> int:
    host = args.host
    config = config_from_args(args, host)
    print(json.dumps(config.to_dict(), indent=2))
    stages_by_slot: dict[str, list[str]] = {}
    for stage, path in missing_slots(config, host):
        stages_by_slot.setdefault(path, []).append(stage)
    for path, stages in stages_by_slot.items():
        print(f"note: stage(s) {', '.join(stages)} cannot run yet: {empty_slot_reason(path, host)}", file=sys.stderr)
    return 0


def _cmd_config_validate(args: argparse.Namespace) -> int:
    host = args.host
    config = resolve_config(args.scene, args.files, args.overrides, host=host)
    print(f"ok: {config.name} (stages: {', '.join(config.stages) or 'none'})")
    return 0


def _cmd_config_scenes(args: argparse.Namespace) -> int:
    host = args.host
    for name in sorted(host.scenes):
        scene = host.scenes[name]
        print(f"{name:16s} {scene.description}")
    return 0


def _cmd_config_stages(args: argparse.Namespace) -> int:
    host = args.host
    for name in sorted(host.stages):
        stage = host.stages[name]
        section = f"[{name}]" if stage.section else "-"
        print(f"{name:12s} {stage.description}")
        print(f"{'':12s}   section: {section}; needs: {', '.join(stage.needs) or '-'}; "
              f"uses: {', '.join(p for p in stage.uses if p not in stage.needs) or '-'}; "
              f"from {stage.source.describe()}")
    return 0


def stage_failure(outcome: StageOutcome) -> VqtouchError:
    """The one-line error for a stage that a command asked for but that did not run."""
    return VqtouchError(f"stage {outcome.stage!r} {outcome.describe()}")


def _cmd_demo(args: argparse.Namespace) -> int:
    from .demo import run_demo, scale_for_demo
    from .runs import RunDir

    host = args.host
    config = config_from_args(args, host)
    if not args.full:
        config = scale_for_demo(config, host)
    run = RunDir.create(config, argv=args.argv, host=host, path=args.out)
    report = run_demo(config, host, run)
    print(f"report: {run.path / 'report.md'}")
    ran = sum(stage["status"].startswith("ran") for stage in report["stages"])
    blocked = sum(stage["status"].startswith("cannot run") for stage in report["stages"])
    failed = sum(stage["status"].startswith("failed") for stage in report["stages"])
    print(f"scene {config.scene}: {ran} of {len(report['stages'])} stages ran, {blocked} cannot run, {failed} failed "
          "(reasons in the report)")
    return 0


def build_parser(host: PluginHost) -> argparse.ArgumentParser:
    """The full parser, including subcommands contributed by ``host``'s plugins."""
    from . import __version__

    parser = argparse.ArgumentParser(
        prog="vqtouch", description="Data-efficient tactile image generation across sensors (VQ-Touch).")
    parser.add_argument("--version", action="version", version=f"vqtouch {__version__}")
    parser.add_argument("--no-progress", action="store_true", help="disable progress bars (also VQTOUCH_NO_PROGRESS=1)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    plugins = sub.add_parser("plugins", help="list every registered plugin, its kind, package and version")
    plugins.add_argument("--kind", help="only this kind (autoencoder, conditioner, stage, scene, ...)")
    plugins.add_argument("--json", action="store_true", help="machine-readable output")
    plugins.set_defaults(handler=_cmd_plugins)

    config = sub.add_parser("config", help="show, validate and list experiment configs and scenes")
    config_sub = config.add_subparsers(dest="config_command", metavar="ACTION", required=True)
    show = config_sub.add_parser("show", help="print the resolved config of a scene (JSON)")
    add_config_arguments(show, scene_required=True)
    show.set_defaults(handler=_cmd_config_show)
    validate = config_sub.add_parser("validate", help="validate config files (optionally over a scene)")
    validate.add_argument("files", nargs="+", metavar="FILE", help="TOML or JSON config files")
    validate.add_argument("--scene", help="scene preset the files are merged over")
    validate.add_argument("--set", action="append", default=[], dest="overrides", metavar="PATH=VALUE")
    validate.set_defaults(handler=_cmd_config_validate)
    scenes = config_sub.add_parser("scenes", help="list the scene presets")
    scenes.set_defaults(handler=_cmd_config_scenes)
    stages = config_sub.add_parser("stages", help="list the pipeline stages: section, slots, plugin")
    stages.set_defaults(handler=_cmd_config_stages)

    demo = sub.add_parser("demo", help="run a scene end to end on the embedded data and write a report")
    add_config_arguments(demo, default_scene="reconstruction")
    demo.add_argument("--out", help="run directory (default: <output_dir>/<name>-<time>-<hash>)")
    demo.add_argument("--full", action="store_true",
                      help="run the scene at its configured size (default: scaled down to minutes on a CPU)")
    demo.set_defaults(handler=_cmd_demo)

    host.pm.hook.vqtouch_add_commands(subparsers=sub)
    parser.set_defaults(host=host)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``vqtouch`` command; returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        parser = build_parser(load_plugins())
        args = parser.parse_args(argv)
        if args.no_progress:
            disable_progress()
        if not getattr(args, "handler", None):
            parser.print_help()
            return 2
        args.argv = ["vqtouch", *argv]
        return int(args.handler(args) or 0)
    except VqtouchError as exc:
        print(f"vqtouch: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("vqtouch: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

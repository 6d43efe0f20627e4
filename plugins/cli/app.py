"""The ``vqtouch`` command line.

``main(argv) -> int`` builds an argparse parser whose subcommands come from core (``plugins``,
``config``) and from plugins (``vqtouch_add_commands``; the built-in ``demo`` and ``report`` come from
the report plugin, every ``train``/``evaluate`` command from its stage's).  User errors print one
line, ``vqtouch: error: ...``, and exit with status 2.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import signal
import sys
import threading
import traceback
import warnings
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, NoReturn

from vqtouch.core.config import resolve_config
from vqtouch.core.errors import ConfigError, VqtouchError
from vqtouch.core.plugin_manager import PluginHost, load_plugins
from vqtouch.plugins.utils.image_options import bad_images_skipped, greyscale_allowed
from vqtouch.plugins.runtime.outputs import check_output, command_inputs, reading
from vqtouch.plugins.utils.progress import disable_progress, progress_forced_off
from vqtouch.core.references import resolve
from vqtouch.plugins.utils.seeding import SEED_MAX
from vqtouch.plugins.utils.threads import command_threads
from vqtouch.core.stages import empty_slot_reason, missing_slots
from vqtouch.plugins.runtime.execution import StageOutcome

from .errors import ENV_DEBUG, _debug_requested, _show_warning, _silence_stdout, user_error_message


def add_config_arguments(
    parser: argparse.ArgumentParser, *, scene_required: bool = False, default_scene: str | None = None
) -> None:
    """Add ``SCENE``/``--scene``, ``--config`` and ``--set`` to a subcommand (for plugin commands too)."""
    if scene_required:
        parser.add_argument(
            "scene_positional", nargs="?", metavar="SCENE", help="scene preset name (see `vqtouch config scenes`)"
        )
        parser.add_argument("--scene", help="the scene as an option, as the other commands take it")
        parser.set_defaults(scene_required=True)
    else:
        parser.add_argument(
            "--scene", help=f"scene preset (default: the one a --config recipe names, else {default_scene})"
        )
        parser.set_defaults(default_scene=default_scene)
    parser.add_argument(
        "--config",
        action="append",
        default=[],
        metavar="FILE",
        help="TOML or JSON config merged over the scene (repeatable, in order)",
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        dest="overrides",
        metavar="PATH=VALUE",
        help="override one value, e.g. --set tokenizer.train.steps=200 (JSON values; repeatable)",
    )


def checkpoint_step(text: str) -> int | str:
    """``--step`` of the commands that read a run: a step number, or ``best`` (the checkpoint with the
    lowest validation loss)."""
    if text == "best":
        return text
    try:
        step = int(text)
    except ValueError:
        step = -1
    if step < 0:
        raise argparse.ArgumentTypeError(f"{text!r} is not a step: give a step number (e.g. 500) or 'best'")
    return step


class NumberType:
    """An argparse ``type`` for a number in a range: refuses text that is not a number, NaN and the
    infinities (a float), a fraction (an integer) and anything out of ``[low, high]`` (``low_open``
    / ``high_open``: the bound itself excluded), each with one line saying what is allowed.
    ``bounds`` lets tests and docs read the range."""

    def __init__(
        self,
        kind: type,
        low: float | None = None,
        high: float | None = None,
        *,
        low_open: bool = False,
        high_open: bool = False,
        what: str = "",
    ) -> None:
        self.kind, self.low, self.high, self.low_open, self.high_open = kind, low, high, low_open, high_open
        self.__name__ = what or ("integer" if kind is int else "number")  # argparse names the type by it

    @property
    def bounds(self) -> tuple[float | None, float | None, bool, bool]:
        return self.low, self.high, self.low_open, self.high_open

    def describe(self) -> str:
        noun = "an integer" if self.kind is int else "a finite number"
        low, high = (f"{bound:d}" if self.kind is int else f"{bound:g}" for bound in (self.low or 0, self.high or 0))
        if self.low is not None and self.high is not None:
            left, right = "(" if self.low_open else "[", ")" if self.high_open else "]"
            return f"{noun} in {left}{low}, {high}{right}"
        if self.low is not None:
            return f"{noun} {'>' if self.low_open else '>='} {low}"
        return noun

    def __call__(self, text: str) -> int | float:
        try:
            value = int(text) if self.kind is int else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {self.describe()}") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"{text}: must be {self.describe()}")
        too_low = self.low is not None and (value <= self.low if self.low_open else value < self.low)
        too_high = self.high is not None and (value >= self.high if self.high_open else value > self.high)
        if too_low or too_high:
            raise argparse.ArgumentTypeError(f"{text}: must be {self.describe()}")
        return value


#: Integers of at least 1 / at least 0.
positive_int = NumberType(int, 1, what="positive_int")
non_negative_int = NumberType(int, 0, what="non_negative_int")
#: A seed (``--seed``, ``--seeds``): an integer in [0, SEED_MAX].
seed_int = NumberType(int, 0, SEED_MAX, what="seed")
#: Classifier-free guidance scales (1: unguided), as ``generator.guidance`` allows them.
guidance_scale = NumberType(float, 0, 1000, what="guidance")
#: Truncation: the probability mass of the most likely codes kept, in (0, 1].
truncation_mass = NumberType(float, 0, 1, low_open=True, what="truncation")
#: A share of something, in [0, 1].
fraction = NumberType(float, 0, 1, what="fraction")
#: A distance threshold: a finite number of at least 0.
non_negative_float = NumberType(float, 0, what="non_negative_float")
#: Family images per shot of an unseen sensor (``--ratio``), in [0, 1000]: more renders millions of images.
family_ratio = NumberType(float, 0, 1000, what="ratio")
#: A learning rate, as the training sections allow it: (0, 10].
learning_rate = NumberType(float, 0, 10, low_open=True, what="learning_rate")


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose errors are one line, like every other vqtouch error: what was wrong
    and where to read the command's options (rather than its whole usage first)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"vqtouch: error: {self.prog}: {message} (see {self.prog} --help)\n")


def add_greyscale_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``--allow-greyscale`` to a command that reads image files the user gives: greyscale images
    are then copied into 3 channels instead of refused (:func:`vqtouch.plugins.utils.images.greyscale_allowed`)."""
    parser.add_argument(
        "--allow-greyscale", action="store_true", help="accept greyscale images (copied into 3 channels)"
    )


def add_image_folder_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--allow-greyscale`` and ``--lenient`` to a command that reads folders of images the user
    gives (:func:`add_greyscale_argument`; :func:`vqtouch.plugins.utils.images.bad_images_skipped`)."""
    add_greyscale_argument(parser)
    parser.add_argument(
        "--lenient",
        action="store_true",
        help="skip images that do not decode, with one warning naming them (default: refuse the folder)",
    )


def add_overwrite_argument(parser: argparse.ArgumentParser, finished: str) -> None:
    """Add ``--overwrite`` to a command that writes ``finished`` (e.g. ``cluster.json``; ``.``: ``--out``
    is that file) into its ``--out``: without the flag, an ``--out`` that holds it is refused before the
    command runs (:func:`refuse_finished_output`)."""
    parser.add_argument("--overwrite", action="store_true", help=f"replace the {finished} that --out holds")
    parser.set_defaults(finished_output=finished)


def refuse_finished_output(args: argparse.Namespace) -> None:
    """ConfigError when ``--out`` holds the finished result the command declared
    (:func:`add_overwrite_argument`) and ``--overwrite`` is not given: nothing written is lost."""
    finished = getattr(args, "finished_output", None)
    if not finished or getattr(args, "overwrite", False) or not getattr(args, "out", None):
        return
    path = Path(args.out) if finished == "." else Path(args.out) / finished
    if path.exists():
        raise ConfigError(
            f"--out {args.out} already holds {path.name}; pass --overwrite to replace it, or choose another --out"
        )


def option_given(args: argparse.Namespace, option: str) -> bool:
    """Whether the user typed ``option`` (e.g. ``--best-of-rank``) on the command line, rather than
    leaving its default: for an option that has no effect without another."""
    return any(token == option or token.startswith(option + "=") for token in getattr(args, "argv", ()))


def add_step_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``--step N|best`` (default: the run's newest good checkpoint) to a command that reads a run."""
    parser.add_argument(
        "--step",
        type=checkpoint_step,
        metavar="N|best",
        help="checkpoint step, or 'best' for the lowest validation loss (default: the newest complete checkpoint)",
    )


def add_run_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--out``, ``--resume`` and ``--overwrite`` to a command that trains into a run directory
    (see :func:`training_run`)."""
    parser.add_argument("--out", help="run directory (default: <output_dir>/<name>-<time>-<hash>)")
    parser.add_argument("--resume", metavar="RUN", help="continue an interrupted run from its last checkpoint")
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="empty the --out run directory first (refused for a folder that holds no run)",
    )


def training_run(
    args: argparse.Namespace,
    host: PluginHost,
    prepare: Callable[[Any], Any] | None = None,
    reads: Sequence[tuple[str, str, Any]] = (),
    stage: str | None = None,
) -> tuple[Any, Any]:
    """The run directory and config of a training command (:func:`add_run_arguments`): the run named
    by ``--resume`` (locked for writing, its saved config), else a new run of the config the
    command's arguments resolve to, after ``prepare(config)`` (e.g. a command's own flags).
    ``reads``: the command's inputs as ``(flag, what, path)``, which ``--out`` may not be or hold.
    ``stage``: the stage the command trains; ``--resume`` refuses a run whose stages lack it (a run
    knows its kind), before anything is written."""
    from vqtouch.plugins.runtime.run_dir import RunDir

    if args.resume:
        if args.overwrite:
            raise ConfigError("--overwrite starts a new run and --resume continues one; give one of them")
        if args.overrides or args.config:
            raise ConfigError("--resume continues a run with its saved config; drop --set/--config")
        # The run's kind is checked before it is locked: a refused --resume writes nothing.
        config = RunDir.open(args.resume).load_config(host)
        if stage is not None and stage not in config.stages:
            raise ConfigError(
                f"--resume {args.resume}: this run has no {stage} stage (its stages: {', '.join(config.stages)}); "
                f"resume a {stage} run, or start one with --out"
            )
        run = RunDir.open(args.resume, for_writing=True)
        if not (run.path / "env.json").is_file():  # stopped while it was being created: record it now
            from vqtouch.plugins.runtime.records import environment_record

            run.write_json("env.json", environment_record(config, args.argv, host))
        return run, config
    config = config_from_args(args, host)
    if prepare is not None:
        config = prepare(config)
    run = RunDir.create(config, argv=args.argv, host=host, path=args.out, overwrite=args.overwrite, reads=reads)
    return run, config


def plugin_block(text: str, flag: str, default_name: str | None = None) -> dict[str, Any]:
    """A plugin given on the command line (``--sensor``, ``--dataset``, ...): its name, or a JSON object of
    the plugin and its options (``"name"`` defaults to ``default_name`` when one is given).  Bad JSON or a
    block without a name is a ConfigError naming ``flag``."""
    text = text.strip()
    if not text.startswith("{"):
        return {"name": text}
    try:
        block = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{flag} is not valid JSON: {exc}") from None
    if isinstance(block, dict) and default_name is not None:
        block = {"name": default_name, **block}
    if not isinstance(block, dict) or "name" not in block:
        raise ConfigError(
            f'{flag}: a JSON block needs the plugin\'s "name", e.g. {{"name": "image_folder", "root": "data/frames"}}'
        )
    return block


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
    return resolve_config(
        positional or scene,
        args.config,
        args.overrides,
        host=host,
        default_scene=getattr(args, "default_scene", None),
        scene_required=getattr(args, "scene_required", False),
    )


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
        print(
            f"{'':12s}   section: {section}; needs: {', '.join(stage.needs) or '-'}; "
            f"uses: {', '.join(p for p in stage.uses if p not in stage.needs) or '-'}; "
            f"from {stage.source.describe()}"
        )
    return 0


def stage_failure(outcome: StageOutcome) -> VqtouchError:
    """The one-line error for a stage that a command asked for but that did not run."""
    return VqtouchError(f"stage {outcome.stage!r} {outcome.describe()}")


def build_parser(host: PluginHost) -> argparse.ArgumentParser:
    """The full parser, including subcommands contributed by ``host``'s plugins."""
    from vqtouch.core import __version__

    parser = OneLineParser(
        prog="vqtouch", description="Data-efficient tactile image generation across sensors (VQ-Touch)."
    )
    parser.add_argument("--version", action="version", version=f"vqtouch {__version__}")
    parser.add_argument("--no-progress", action="store_true", help="disable progress bars (also VQTOUCH_NO_PROGRESS=1)")
    parser.add_argument(
        "--threads",
        type=non_negative_int,
        help="torch CPU threads (default: the free cores; 1 when the load exceeds the cores, said in one "
        "line; 0: torch's default; also VQTOUCH_THREADS)",
    )
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

    host.pm.hook.vqtouch_add_commands(subparsers=sub)
    parser.set_defaults(host=host)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``vqtouch`` command; returns the exit status.

    A user error prints one line, ``vqtouch: error: ...``, and returns 2 (``--debug`` or
    ``VQTOUCH_DEBUG=1`` print the traceback first); Ctrl-C returns 130; a closed stdout
    (``vqtouch plugins | head``) returns 141 quietly, as SIGPIPE would.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = _debug_requested(argv)
    with warnings.catch_warnings():
        if not debug:
            warnings.showwarning = _show_warning
        return _main(argv, debug)


class Terminated(KeyboardInterrupt):
    """SIGTERM (what schedulers and ``kill`` send) outside training: stops the command like Ctrl-C,
    so that what it was writing is cleaned up or left resumable, and exits 143."""

    def __init__(self, signum: int) -> None:
        super().__init__(f"signal {signum}")
        self.signum = signum


@contextlib.contextmanager
def _sigterm_interrupts() -> Iterator[None]:
    """While a command runs, SIGTERM raises :class:`Terminated` (the trainer installs its own handler
    while it fits, which stops after the current step instead).  Left alone where SIGTERM is ignored
    on purpose or outside the main thread."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGTERM) is signal.SIG_IGN:
        yield
        return

    def terminate(signum: int, frame: Any) -> None:
        raise Terminated(signum)

    previous = signal.signal(signal.SIGTERM, terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _main(argv: list[str], debug: bool) -> int:
    bars_were_off = progress_forced_off()
    try:
        return _run_command(argv, debug)
    finally:
        disable_progress(bars_were_off)  # `--no-progress` of one command does not outlive it


def _run_command(argv: list[str], debug: bool) -> int:
    try:
        parser = build_parser(load_plugins())
        parser.add_argument(
            "--debug", action="store_true", help=f"on an error, show the full traceback (also {ENV_DEBUG}=1)"
        )
        try:
            args = parser.parse_args(argv)
        except SystemExit as exc:  # --help, --version, or a bad argument (its one line already printed)
            return exc.code if isinstance(exc.code, int) else 2
        if args.no_progress:
            disable_progress()  # for this command only (see the finally below)
        if not getattr(args, "handler", None):
            parser.print_help()
            return 2
        args.argv = ["vqtouch", *argv]
        command, reads = command_inputs(parser, args)
        # A handler given as a reference imports its implementation (and torch) here, not at start-up,
        # and before command_threads, which sets torch's threads only for a command that imported it.
        handler = resolve(args.handler, f"the handler of 'vqtouch {command}'")
        with (
            reading(reads, command),
            _sigterm_interrupts(),
            greyscale_allowed(bool(getattr(args, "allow_greyscale", False))),
            bad_images_skipped(bool(getattr(args, "lenient", False))),
            command_threads(args.threads) as busy,
        ):
            if busy:
                print(f"vqtouch: note: {busy}", file=sys.stderr, flush=True)
            if getattr(args, "out", None):  # before the handler loads or trains anything
                check_output(args.out, into_package=command == "pretrained export")
                refuse_finished_output(args)
            status = int(handler(args) or 0)
        if sys.stdout is not None:  # None when the shell closed it (`>&-`): print() then writes nothing
            sys.stdout.flush()  # a reader that went away shows here, not in the flush at exit
        return status
    except BrokenPipeError:
        _silence_stdout()
        return 141  # 128 + SIGPIPE: what a shell reports for a command stopped by a closed pipe
    except KeyboardInterrupt as exc:
        if debug:
            traceback.print_exc()
        signum = getattr(exc, "signum", None)
        print(f"vqtouch: {'terminated (SIGTERM)' if signum else 'interrupted'}", file=sys.stderr)
        return 128 + signum if signum else 130
    except Exception as exc:  # noqa: BLE001 - only user errors are caught; the rest is re-raised
        message = user_error_message(exc)
        if message is None:
            raise
        if debug:
            traceback.print_exc()
        print(f"vqtouch: error: {message}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

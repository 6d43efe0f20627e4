"""Run directories: every run keeps its resolved config, its environment and its outputs.

Layout::

    <output_dir>/<name>-<YYYYmmdd-HHMMSS>-<config hash>/
        config.json     the fully resolved ExperimentConfig
        env.json        versions, plugins, command line, seed, git revision
        metrics.jsonl   one JSON object per logged step
        products.json   what each stage made, by product name (see :meth:`RunDir.publish`)
        checkpoints/    step-NNNNNNNN/ folders, one safetensors file per trained component (the
                        tokenizer's; another trained stage keeps its own in checkpoints/<stage>/)
        .vqtouch.lock   advisory lock of the process writing the run (holds its pid)

A folder holds one run.  :meth:`RunDir.create` refuses a folder that already holds files
(``overwrite=True`` empties a run directory first, never another folder), and one process at a
time writes a run: :meth:`RunDir.create` and ``RunDir.open(..., for_writing=True)`` take an
``fcntl.flock`` on ``.vqtouch.lock``, which the operating system releases when the process ends,
however it ends.  Readers take no lock.  Whatever reads a run's weights asks :meth:`RunDir.checkpoint`,
which also checks that the files were made with the run's own config.

Stages hand what they made to later stages and commands through the run, not through imports:
a stage publishes a product (``job.publish("families", "cluster")``) under a name its
registration declares (``makes=("families",)``), and a reader asks the run for it
(``run.product("families", host)``), which names the stage that makes it when it is missing.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import shutil
import time
import warnings
import weakref
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from vqtouch.core.checkpoint import atomic_write, read_metadata
from vqtouch.core.config import ExperimentConfig, validate_experiment
from vqtouch.plugins.utils.files import FileModel, check_model, inside_root
from vqtouch.plugins.runtime.outputs import LOCK_NAME, check_output
from vqtouch.plugins.runtime.records import config_hash, environment_record, recorded_config
from vqtouch.core.errors import CheckpointError, ConfigError, VqtouchError, VqtouchWarning, unknown_name_message

if TYPE_CHECKING:
    from vqtouch.core.plugin_manager import PluginHost


try:
    import fcntl
except ImportError:  # pragma: no cover - Windows has no flock; runs there are simply not locked
    fcntl = None

#: A folder with a run's lock file but no config.json, as the messages describe it.
_CONFIGLESS_RUN = (
    "a run without its config.json (stopped while it was being created, or the file was deleted), which cannot "
    "be resumed"
)
#: The index of what the run's stages made (:meth:`RunDir.publish`, :meth:`RunDir.product`).
PRODUCTS_FILE = "products.json"


class ProductEntry(FileModel):
    """One product of a run's products.json: the stage that made it and its path inside the run."""

    stage: str
    path: str
    facts: dict[str, Any] = {}


@dataclass(frozen=True)
class Product:
    """Something a stage made and published in its run: ``path`` (a file or folder inside the
    run), the ``stage`` that made it, and ``facts`` the stage recorded with it (e.g. ``step``)."""

    name: str
    stage: str
    path: Path
    facts: dict[str, Any] = field(default_factory=dict)


class MissingProductError(VqtouchError):
    """A run does not hold the product asked for; the message names the stage that makes it."""


class StartedAfreshWarning(VqtouchWarning):
    """A run directory that held only the config of a run that produced nothing was started afresh."""


class MissingCheckpointError(CheckpointError):
    """A run has no (complete) checkpoint to read, as opposed to one that is wrong."""


def is_main_process() -> bool:
    """False in the ranks other than 0 of a ``torchrun`` launch: they share rank 0's run
    directory, and rank 0 alone creates, locks and writes it."""
    return int(os.environ.get("WORLD_SIZE", "1")) <= 1 or int(os.environ.get("RANK", "0")) == 0


class RunDir:
    """A run's output folder; create one with :meth:`create`, reopen one with :meth:`open`.

    A RunDir that writes holds the run's lock until :meth:`close` (or the end of the process);
    it is also a context manager that closes on exit.
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self.checkpoints = path / "checkpoints"
        self._unlock: weakref.finalize | None = None

    @classmethod
    def create(
        cls,
        config: ExperimentConfig,
        *,
        argv: Sequence[str] | None = None,
        host: PluginHost | None = None,
        path: str | Path | None = None,
        overwrite: bool = False,
        reads: Sequence[tuple[str, str, str | Path | None]] = (),
    ) -> RunDir:
        """Make the folder (under ``config.output_dir`` unless ``path`` is given), lock it and write
        config/env.

        ``reads``: what the command reads, as ``(flag, what, path)``; a run folder that is one of
        them, or holds one, is refused before anything is written or emptied
        (:func:`vqtouch.plugins.runtime.outputs.check_output`).

        A folder that already holds files is refused (ConfigError naming ``--resume`` and
        ``--overwrite``); with ``overwrite`` a run directory (one with a config.json or a
        lock file) is emptied first.  A folder that holds files but no run is never emptied.
        """
        if path is None:
            stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
            path = Path(config.output_dir) / f"{config.name}-{stamp}-{config_hash(config)}"
        run = cls(Path(path))
        check_output(run.path, reads)
        if not is_main_process():
            return run
        # Checked before locking too, so that a refused foreign folder does not get a lock file.
        run._refuse_foreign_folder()
        try:
            run.path.mkdir(parents=True, exist_ok=True)
        except (FileExistsError, NotADirectoryError):
            raise ConfigError(f"{run.path} is a file, not a folder; choose another --out") from None
        run._lock()
        try:
            # Checked again under the lock: the folder may have changed since the check above.
            run._refuse_foreign_folder()
            if run._contents() and not overwrite and run._holds_no_results():
                # A run that stopped before writing anything (bad data, a full disk) holds only its
                # config: starting it again must not need --overwrite.
                warnings.warn(
                    f"{run.path} holds a run that stopped before writing any result; starting afresh in it",
                    StartedAfreshWarning,
                    stacklevel=2,
                )
                overwrite = True
            if run._contents():
                if not overwrite and not (run.path / "config.json").is_file():
                    raise ConfigError(
                        f"{run.path} holds {_CONFIGLESS_RUN}; start it afresh with --overwrite, or choose another --out"
                    )
                if not overwrite:
                    raise ConfigError(
                        f"{run.path} already holds a run; continue it with --resume {run.path}, start it "
                        "afresh with --overwrite, or choose another --out"
                    )
                for entry in run._contents():
                    if entry.is_dir() and not entry.is_symlink():
                        shutil.rmtree(entry)
                    else:
                        entry.unlink()
            run.write_json("config.json", recorded_config(config, host))
            run.write_json("env.json", environment_record(config, argv, host))
            run.checkpoints.mkdir(exist_ok=True)
        except BaseException:
            run.close()
            raise
        return run

    @classmethod
    def open(cls, path: str | Path, *, for_writing: bool = False) -> RunDir:
        """An existing run directory (one with a config.json); ConfigError otherwise.

        ``for_writing`` (resuming a run) takes the run's lock: a run that another process is
        writing is refused with that process's pid.
        """
        run = cls(Path(path))
        if not (run.path / "config.json").is_file():
            if (run.path / LOCK_NAME).exists():
                raise ConfigError(f"{run.path}: {_CONFIGLESS_RUN}; start it afresh with --overwrite --out {run.path}")
            raise ConfigError(f"{run.path}: not a run directory (no config.json)")
        if for_writing and is_main_process():
            run._lock()
        return run

    def close(self) -> None:
        """Release the run's lock (a no-op for readers and when already released)."""
        if self._unlock is not None:
            self._unlock()
            self._unlock = None

    def __enter__(self) -> RunDir:
        return self

    def __exit__(self, *exc_info: Any) -> None:
        self.close()

    def _contents(self) -> list[Path]:
        return [entry for entry in self.path.iterdir() if entry.name != LOCK_NAME] if self.path.is_dir() else []

    def _holds_no_results(self) -> bool:
        """Whether the folder holds a run's config and environment and nothing else (no metrics, no
        checkpoint, no output): a run that failed before its first step."""
        for entry in self._contents():
            if entry.name in ("config.json", "env.json") and entry.is_file():
                continue
            if entry == self.checkpoints and entry.is_dir() and not any(entry.iterdir()):
                continue
            return False
        return True

    def _refuse_foreign_folder(self) -> None:
        # The lock file counts: a run being created holds only it and config.json's temporary file.
        if self._contents() and not any((self.path / name).is_file() for name in ("config.json", LOCK_NAME)):
            raise ConfigError(
                f"{self.path} is not empty and is not a run directory (no config.json); choose an "
                "empty or new --out (--overwrite only empties run directories)"
            )

    def _lock(self) -> None:
        if fcntl is None:  # pragma: no cover
            return
        lock_path = self.path / LOCK_NAME
        fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _lock_holder(fd)
            os.close(fd)
            raise ConfigError(
                f"{self.path} is in use by another vqtouch process (pid {holder}); wait for it to "
                "finish or stop it, or choose another --out"
            ) from None
        except BaseException:
            os.close(fd)
            raise
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        # Closing the descriptor releases the lock; finalize also does it when the RunDir is
        # garbage-collected, and the OS when the process dies.
        self._unlock = weakref.finalize(self, os.close, fd)

    def checkpoint(
        self,
        host: PluginHost,
        step: int | str | None = None,
        required_files: Sequence[str] = (),
        stage: str | None = None,
    ) -> Path:
        """The run's checkpoint folder to read: the newest complete, readable ``checkpoints/step-*``
        folder, the one of ``step``, or with ``step="best"`` the one with the lowest validation
        loss (recorded by the trainer, see ``keep_best``); the one function every reader of a
        run's weights goes through (resume, reconstruct, evaluate, generate, adapt).

        Newer folders that are incomplete or unreadable (an interrupted save, a truncated or
        missing module file) are skipped with a :class:`~vqtouch.plugins.training.checkpoints.SkippedCheckpointWarning`
        naming them.  ``required_files`` are the files the caller needs in the folder (e.g. a
        tokenizer's ``autoencoder.safetensors``).  Every component file in the folder must have
        been made with the config of one of the slots of the run's config.json, else
        CheckpointError (the folder mixes two runs).  No usable checkpoint:
        :class:`MissingCheckpointError`, which says why when step folders exist.
        ``stage``: read the checkpoints that a trained stage other than the tokenizer keeps in
        ``checkpoints/<stage>/``.
        """
        from vqtouch.plugins.training.checkpoints import (
            checkpoint_problem,
            latest_good_checkpoint,
            no_good_checkpoint,
            step_folders,
        )

        checkpoints = self.checkpoints / stage if stage else self.checkpoints
        if step == "best":
            step = self.best_step(host, required_files, stage=stage)
        if step is None:
            folder = latest_good_checkpoint(checkpoints, required_files=required_files)
            if folder is None:
                if not step_folders(checkpoints):
                    where = f"checkpoints/{stage}/" if stage else "checkpoints/"
                    raise MissingCheckpointError(f"{self.path}: no checkpoint in {where}; train this run first")
                raise MissingCheckpointError(
                    f"{no_good_checkpoint(checkpoints, required_files)}; restore a step "
                    "folder from a copy, or train the run again with --overwrite"
                )
        else:
            folder = checkpoints / f"step-{step:08d}"
            if not folder.is_dir():
                steps = [number for number, _ in step_folders(checkpoints)]
                have = f"this run has steps {', '.join(map(str, steps))}" if steps else "this run has no checkpoint"
                raise MissingCheckpointError(f"{folder}: no such checkpoint; {have}")
            problem = checkpoint_problem(folder, required_files)
            if problem is not None:
                raise MissingCheckpointError(f"{folder}: unusable checkpoint ({problem}); choose another step")
        self._check_files(folder, host)
        return folder

    def resume(
        self, trainer: Any, host: PluginHost, *, stage: str | None = None, required_files: Sequence[str] = ()
    ) -> bool:
        """Put ``trainer`` at this run's newest good checkpoint (of ``stage``'s folder, see
        :meth:`checkpoint`), checked against the run's config; prints where it resumed.

        A run without any step folder starts from step 0, dropping the metric lines an
        interrupted attempt logged; step folders that are all unusable raise
        :class:`MissingCheckpointError` rather than silently starting over.  Returns whether a
        checkpoint was loaded.
        """
        from vqtouch.plugins.training.checkpoints import step_folders

        checkpoints = self.checkpoints / stage if stage else self.checkpoints
        folder = (
            self.checkpoint(host, stage=stage, required_files=required_files)
            if step_folders(checkpoints)
            else checkpoints
        )
        if not trainer.resume(folder):
            return False
        print(f"resumed {self.path} at step {trainer.state.step} ({folder.name})")
        return True

    def best_step(self, host: PluginHost, required_files: Sequence[str] = (), stage: str | None = None) -> int:
        """The step whose checkpoint scored best on the held-out split, as the newest good checkpoint's
        trainer state records it; MissingCheckpointError when the run kept none."""
        from vqtouch.plugins.training.checkpoints import read_trainer_meta

        newest = self.checkpoint(host, required_files=required_files, stage=stage)
        best = read_trainer_meta(newest).get("best_step")
        if best is None:
            raise MissingCheckpointError(
                f"{self.path}: no best checkpoint recorded (the run scored no held-out "
                "samples: train.keep_best=false or data.val_fraction=0); give a step number"
            )
        return int(best)

    def _check_files(self, folder: Path, host: PluginHost) -> None:
        from vqtouch.plugins.training.checkpoints import TRAINER_STATE

        config = self.load_config(host)
        slots: dict[str, list[tuple[str, dict[str, Any]]]] = {}  # kind -> [(slot, plugin config)]
        for path, info in host.slots.items():
            value = config.slot(path)
            items = list(enumerate(value)) if info.many else [(None, value)]
            for index, item in items:
                if item is not None:
                    slot = path if index is None else f"{path}.{index}"
                    slots.setdefault(info.kind, []).append((slot, item.model_dump(mode="json")))
        for file in sorted(folder.glob("*.safetensors")):
            if file.name == TRAINER_STATE:
                continue
            metadata = read_metadata(file)
            kind, plugin = metadata.get("vqtouch.component", ""), metadata.get("vqtouch.plugin", "")
            try:
                made_with = json.loads(metadata["vqtouch.config"])
            except (KeyError, json.JSONDecodeError):
                raise CheckpointError(f"{file}: damaged vqtouch header (no readable vqtouch.config)") from None
            candidates = slots.get(kind, [])
            # As written, and as the installed plugin reads it today: an option added since the file was
            # saved takes its default, which must compute what the file did (docs/architecture.md).
            installed = _as_installed(host, kind, made_with)
            readings = {_canonical(made_with), _canonical(installed)}
            if any(_canonical(slot_config) in readings for _, slot_config in candidates):
                continue
            # Name only real differences: an option the file predates is not one.
            raise CheckpointError(
                f"{file} was made with {kind} {plugin!r}{_mismatch(installed, candidates)}; "
                "this folder mixes two runs: pick one of this run's own steps with --step, or "
                "retrain into an empty --out"
            )

    def load_config(self, host: PluginHost) -> ExperimentConfig:
        """The run's resolved config, validated against ``host``.

        A plugin the run used that is no longer installed is named with its distribution (from
        env.json), rather than answered with the closest installed name.
        """
        data = read_run_json(self.path / "config.json")
        env_path = self.path / "env.json"
        env = read_run_json(env_path) if env_path.is_file() else {}
        for name, source in env.get("sections", {}).items():
            if name in data and name not in host.experiment_model.model_fields:
                package = source.get("package") or source.get("plugin")
                version = f" {source['version']}" if source.get("version") else ""
                raise ConfigError(
                    f"{self.path}: its config section {name!r} belongs to stage {source['stage']!r} from "
                    f"{package}{version} (plugin {source['plugin']!r}), which is not installed here; "
                    f"pip install {package}"
                )
        recorded = env.get("components", {})
        for key, source in recorded.items():
            if source["name"] not in host.registry(source["kind"]):
                package = source.get("package") or source.get("plugin")
                version = f" {source['version']}" if source.get("version") else ""
                raise ConfigError(
                    f"{self.path}: {key} uses {source['kind']} {source['name']!r} from {package}{version} "
                    f"(plugin {source['plugin']!r}), which is not installed here; pip install {package}"
                )
        return validate_experiment(data, host)

    def publish(self, name: str, path: str | Path, *, stage: str, **facts: Any) -> Product:
        """Record that ``stage`` made product ``name`` at ``path`` (inside the run: relative to it,
        absolute, or built from the run's path), with JSON-ready ``facts``.  Publishing a name again replaces its entry;
        the index is rewritten atomically, so a reader never sees half of it.  Stages publish
        through :meth:`StageJob.publish <vqtouch.core.StageJob.publish>`, which checks the name
        against the stage's ``makes``."""
        given = Path(path)
        # A path built from the run's own (``job.run.path / "x"``, a trainer's step folder) is taken as
        # it is, even when the run's path is relative; any other relative path is relative to the run.
        target = given if given.is_absolute() or given.is_relative_to(self.path) else self.path / given
        try:
            relative = target.resolve().relative_to(self.path.resolve())
        except ValueError:
            raise ValueError(
                f"product {name!r} of stage {stage!r}: {target} is outside the run {self.path}; "
                "a stage publishes only what it wrote inside its run"
            ) from None
        if not target.exists():
            raise ValueError(
                f"product {name!r} of stage {stage!r}: {target} does not exist; publish a product after writing it"
            )
        index = self._product_index()
        index[name] = {"stage": stage, "path": relative.as_posix(), "facts": json.loads(json.dumps(facts))}
        self.write_json(PRODUCTS_FILE, index)
        return self._product(name, index[name])

    def products(self) -> dict[str, Product]:
        """Every product the run's stages published, by name."""
        return {name: self._product(name, entry) for name, entry in self._product_index().items()}

    def product(self, name: str, host: PluginHost | None = None) -> Product:
        """The product ``name`` a stage of this run published.

        :class:`MissingProductError` when the run holds none (naming the stage that makes it,
        when ``host`` is given) or when its file is gone.  With ``host``, a name no registered
        stage makes is refused listing the names that exist.
        """
        makers = product_makers(host) if host is not None else {}
        if host is not None and name not in makers:
            raise MissingProductError(unknown_name_message("product", name, makers) + " (no stage makes it)")
        entry = self._product_index().get(name)
        if entry is None:
            made = ", ".join(sorted(self._product_index())) or "nothing yet"
            maker = f"; the {makers[name]!r} stage makes it: run it in this run first" if name in makers else ""
            raise MissingProductError(f"{self.path}: no {name!r} in this run (it holds {made}){maker}")
        product = self._product(name, entry)
        if not product.path.exists():
            raise MissingProductError(
                f"{self.path}: the {name!r} that stage {product.stage!r} made is gone "
                f"({product.path}); run that stage again"
            )
        return product

    def _product_index(self) -> dict[str, Any]:
        path = self.path / PRODUCTS_FILE
        if not path.is_file():
            return {}
        index = read_run_json(path)
        if not isinstance(index, dict):
            raise ConfigError(
                f"{path}: not a products index (expected {{name: {{stage, path, facts}}}}); "
                "run the stages that made them again, or delete the file"
            )
        for name, entry in index.items():
            check_model(entry, ProductEntry, f"{path} (product {name!r})")
        return index

    def _product(self, name: str, entry: Mapping[str, Any]) -> Product:
        inside_root(entry["path"], self.path, self.path / PRODUCTS_FILE)
        return Product(name, entry["stage"], self.path / entry["path"], dict(entry.get("facts") or {}))

    def write_json(self, name: str, data: Any) -> Path:
        """Write ``data`` as indented JSON to ``name`` inside the run, atomically."""
        text = json.dumps(data, indent=2, sort_keys=True, default=str) + "\n"
        return atomic_write(self.path / name, lambda tmp: tmp.write_text(text, encoding="utf-8"))

    def write_text(self, name: str, text: str) -> Path:
        """Write a text file (e.g. report.md) inside the run, atomically."""
        return atomic_write(self.path / name, lambda tmp: tmp.write_text(text, encoding="utf-8"))

    def log_metrics(self, stage: str, step: int, metrics: Mapping[str, float]) -> None:
        """Append one line to metrics.jsonl."""
        record = {"stage": stage, "step": step, **{key: float(value) for key, value in metrics.items()}}
        with open(self.path / "metrics.jsonl", "a", encoding="utf-8") as handle:
            handle.write(json.dumps(record, sort_keys=True) + "\n")


def product_makers(host: PluginHost) -> dict[str, str]:
    """Which registered stage makes each product name (the stages' ``makes``)."""
    return {product: stage.name for stage in host.stages.values() for product in stage.makes}


def _canonical(value: Any) -> str:
    return json.dumps(value, sort_keys=True, separators=(",", ":"))


def _as_installed(host: PluginHost, kind: str, made_with: dict[str, Any]) -> dict[str, Any]:
    """A checkpoint header's component config validated by the installed plugin (its defaults filled
    in), or as written when the plugin is gone or no longer accepts it."""
    try:
        return host.validate(kind, made_with).model_dump(mode="json")
    except VqtouchError:
        return made_with


def _lock_holder(fd: int) -> str:
    """The pid written in a lock file that another process holds ("unknown" if unreadable)."""
    # The holder writes its pid right after locking: give it a moment when the file is still empty.
    for _ in range(20):
        text = os.pread(fd, 32, 0).decode(errors="replace").strip()
        if text:
            return text
        time.sleep(0.025)
    return "unknown"


def _mismatch(made_with: dict[str, Any], candidates: list[tuple[str, dict[str, Any]]]) -> str:
    """`` {differing options} but the run's config.json says <slot> {its values}``, against the
    closest slot of the same kind."""
    if not candidates:
        return " but the run's config.json has no such slot"
    same_plugin = [(slot, config) for slot, config in candidates if config.get("name") == made_with.get("name")]
    if not same_plugin:
        said = ", ".join(f"{slot} is {config.get('name')!r}" for slot, config in candidates)
        return f" but the run's config.json says {said}"

    def differing(config: dict[str, Any]) -> list[str]:
        return sorted(
            key for key in set(made_with) | set(config) if _canonical(made_with.get(key)) != _canonical(config.get(key))
        )

    slot, config = min(same_plugin, key=lambda candidate: len(differing(candidate[1])))
    keys = differing(config)
    shown = lambda values: json.dumps({key: values.get(key) for key in keys}, sort_keys=True)  # noqa: E731
    return f" {shown(made_with)} but the run's config.json says {slot} {shown(config)}"


def read_run_json(path: Path) -> Any:
    """A run's JSON file; ConfigError naming it when it is damaged (json's own error names no file)."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f"{path}: not valid JSON ({exc}); restore it from a copy of the run") from None

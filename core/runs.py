"""Run directories: every run keeps its resolved config, its environment and its outputs.

Layout::

    <output_dir>/<name>-<YYYYmmdd-HHMMSS>-<config hash>/
        config.json     the fully resolved ExperimentConfig
        env.json        versions, plugins, command line, seed, git revision
        metrics.jsonl   one JSON object per logged step
        checkpoints/    safetensors files, one per component
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import importlib.metadata as importlib_metadata
import json
import platform
import subprocess
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from .checkpoint import atomic_write
from .config import ExperimentConfig, validate_experiment
from .errors import ConfigError


def config_hash(config: ExperimentConfig) -> str:
    """First 8 hex digits of the SHA-256 of the resolved config (stable across runs)."""
    text = json.dumps(config.to_dict(), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:8]


def _version(distribution: str) -> str | None:
    try:
        return importlib_metadata.version(distribution)
    except importlib_metadata.PackageNotFoundError:
        return None


def _git_revision() -> str | None:
    try:
        result = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5,
                                cwd=Path(__file__).resolve().parent)
    except (OSError, subprocess.SubprocessError):
        return None
    return result.stdout.strip() or None if result.returncode == 0 else None


def environment_record(config: ExperimentConfig, argv: Sequence[str] | None, host: Any = None) -> dict[str, Any]:
    """What env.json holds: enough to say later exactly what produced a run."""
    import torch

    plugins, components = {}, {}
    if host is not None:
        for name, source in sorted(host.sources.items()):
            plugins[name] = {"module": source.module, "package": source.distribution, "version": source.version}
        components = component_sources(config, host)
    return {
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "argv": list(argv) if argv is not None else list(sys.argv),
        "seed": config.seed,
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "versions": {name: _version(name) for name in
                     ("vqtouch", "torch", "torchvision", "pluggy", "pydantic", "safetensors", "numpy",
                      "scikit-learn", "open_clip_torch")},
        "cuda_available": torch.cuda.is_available(),
        "device_name": torch.cuda.get_device_name(0) if torch.cuda.is_available() else platform.processor() or "cpu",
        "git_revision": _git_revision(),
        "plugins": plugins,
        "components": components,
    }


def component_sources(config: ExperimentConfig, host: Any) -> dict[str, dict[str, Any]]:
    """For every filled slot (``metrics.0`` for list items): the plugin name and where it came from,
    so a later reader of the run can name a distribution that has since been uninstalled."""
    sources: dict[str, dict[str, Any]] = {}
    for path, info in host.slots.items():
        value = config.slot(path)
        items = list(enumerate(value)) if info.many else [(None, value)]
        for index, item in items:
            if item is None:
                continue
            source = host.registry(info.kind).get(item.name).source
            key = path if index is None else f"{path}.{index}"
            sources[key] = {"kind": info.kind, "name": item.name, "plugin": source.plugin,
                            "package": source.distribution, "version": source.version}
    return sources


class RunDir:
    """A run's output folder; create one with :meth:`create`."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.checkpoints = path / "checkpoints"

    @classmethod
    def create(cls, config: ExperimentConfig, *, argv: Sequence[str] | None = None, host: Any = None,
               path: str | Path | None = None) -> RunDir:
        """Make the folder (under ``config.output_dir`` unless ``path`` is given) and write config/env."""
        if path is None:
            stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
            path = Path(config.output_dir) / f"{config.name}-{stamp}-{config_hash(config)}"
        run = cls(Path(path))
        run.path.mkdir(parents=True, exist_ok=True)
        run.checkpoints.mkdir(exist_ok=True)
        run.write_json("config.json", config.to_dict())
        run.write_json("env.json", environment_record(config, argv, host))
        return run

    @classmethod
    def open(cls, path: str | Path) -> RunDir:
        """An existing run directory (one with a config.json); ConfigError otherwise."""
        run = cls(Path(path))
        if not (run.path / "config.json").is_file():
            raise ConfigError(f"{run.path}: not a run directory (no config.json)")
        return run

    def load_config(self, host: Any) -> ExperimentConfig:
        """The run's resolved config, validated against ``host``.

        A plugin the run used that is no longer installed is named with its distribution (from
        env.json), rather than answered with the closest installed name.
        """
        data = json.loads((self.path / "config.json").read_text(encoding="utf-8"))
        env_path = self.path / "env.json"
        recorded = json.loads(env_path.read_text(encoding="utf-8")).get("components", {}) if env_path.is_file() else {}
        for key, source in recorded.items():
            if source["name"] not in host.registry(source["kind"]):
                package = source.get("package") or source.get("plugin")
                version = f" {source['version']}" if source.get("version") else ""
                raise ConfigError(f"{self.path}: {key} uses {source['kind']} {source['name']!r} from {package}{version} "
                                  f"(plugin {source['plugin']!r}), which is not installed here; pip install {package}")
        return validate_experiment(data, host)

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

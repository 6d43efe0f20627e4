"""What a run records of its config and environment: config.json holds the resolved config without
the sections of stages the run does not use (:func:`recorded_config`), env.json the versions,
plugins, command line, seed and git revision (:func:`environment_record`), and a run's folder name
ends in :func:`config_hash`."""

from __future__ import annotations

import datetime as _dt
import hashlib
import importlib.metadata as importlib_metadata
import json
import platform
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from vqtouch.core.config import ExperimentConfig

if TYPE_CHECKING:
    from vqtouch.core.plugin_manager import PluginHost


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
        result = subprocess.run(
            ["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5, cwd=Path(__file__).resolve().parent
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return result.stdout.strip() or None if result.returncode == 0 else None


def environment_record(
    config: ExperimentConfig, argv: Sequence[str] | None, host: PluginHost | None = None
) -> dict[str, Any]:
    """What env.json holds: enough to say later exactly what produced a run."""
    import torch

    plugins, components, sections = {}, {}, {}
    if host is not None:
        for name, source in sorted(host.sources.items()):
            plugins[name] = {"module": source.module, "package": source.distribution, "version": source.version}
        components = component_sources(config, host)
        sections = section_sources(config, host)
    return {
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "argv": list(argv) if argv is not None else list(sys.argv),
        "seed": config.seed,
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "versions": {
            name: _version(name)
            for name in (
                "vqtouch",
                "torch",
                "torchvision",
                "pluggy",
                "pydantic",
                "safetensors",
                "numpy",
                "scikit-learn",
                "open_clip_torch",
            )
        },
        "cuda_available": torch.cuda.is_available(),
        "device_name": torch.cuda.get_device_name(0) if torch.cuda.is_available() else platform.processor() or "cpu",
        "git_revision": _git_revision(),
        "plugins": plugins,
        "components": components,
        "sections": sections,
    }


def used_sections(config: ExperimentConfig, host: PluginHost) -> set[str]:
    """The stage sections a run of ``config`` uses: its stages' own, and those holding a slot its stages
    need or use (the generator stage reads ``tokenizer``).  Core's fields are always used."""
    used = set()
    for name in config.stages:
        stage = host.stage(name)
        used.add(stage.name)
        used.update(path.split(".")[0] for path in stage.slots)
    return used


def stage_section_names(config: ExperimentConfig) -> list[str]:
    """The fields of ``config`` that are stage sections (added by stage plugins), not core's own."""
    return [name for name in type(config).model_fields if name not in ExperimentConfig.model_fields]


def recorded_config(config: ExperimentConfig, host: PluginHost | None = None) -> dict[str, Any]:
    """What a run's config.json holds: the resolved config without the sections of stages the run does
    not use, so installing or removing an unrelated stage plugin never changes or breaks it (without
    ``host`` to say which stages use which sections: all of it)."""
    data = config.to_dict()
    if host is None:
        return data
    used = used_sections(config, host)
    for name in stage_section_names(config):
        if name not in used:
            data.pop(name, None)
    return data


def section_sources(config: ExperimentConfig, host: PluginHost) -> dict[str, dict[str, Any]]:
    """For every stage section the run records: the stage that owns it and where that came from."""
    sources = {}
    owners = {stage.name: stage for stage in host.stages.values() if stage.section is not None}
    for name in sorted(used_sections(config, host) & set(stage_section_names(config))):
        stage = owners.get(name)
        if stage is not None:
            sources[name] = {
                "stage": stage.name,
                "plugin": stage.source.plugin,
                "package": stage.source.distribution,
                "version": stage.source.version,
            }
    return sources


def component_sources(config: ExperimentConfig, host: PluginHost) -> dict[str, dict[str, Any]]:
    """For every filled slot (``metrics.0`` for list items) of the sections the run records: the plugin
    name and where it came from, so a later reader of the run can name a distribution that has since
    been uninstalled."""
    sources: dict[str, dict[str, Any]] = {}
    recorded = set(recorded_config(config, host))
    for path, info in host.slots.items():
        if path.split(".")[0] not in recorded:
            continue
        value = config.slot(path)
        items = list(enumerate(value)) if info.many else [(None, value)]
        for index, item in items:
            if item is None:
                continue
            source = host.registry(info.kind).get(item.name).source
            key = path if index is None else f"{path}.{index}"
            sources[key] = {
                "kind": info.kind,
                "name": item.name,
                "plugin": source.plugin,
                "package": source.distribution,
                "version": source.version,
            }
    return sources

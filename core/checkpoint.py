"""Checkpoints: one ``.safetensors`` file per component, rebuildable from its header alone.

The header metadata (strings only) carries:

=========================  =====================================================
``format``                 ``"pt"`` (safetensors convention)
``vqtouch.format_version`` version of this layout (``FORMAT_VERSION``)
``vqtouch.component``      registry kind (``autoencoder``, ``conditioner``, ...)
``vqtouch.plugin``         registered plugin name, e.g. ``label``
``vqtouch.plugin_source``  pluggy plugin name, distribution and its version (JSON)
``vqtouch.config``         the component's full plugin config (compact JSON)
``vqtouch.context``        the :class:`BuildContext` it was built with (JSON)
``vqtouch.step``           training step the weights belong to
=========================  =====================================================

Writes are atomic (temporary file in the same folder, fsync, rename), so an interrupted
save never replaces a good checkpoint with a broken one; a write that fails (a full disk,
a read-only folder) is a one-line :class:`CheckpointError` naming the file, the cause and the
fix.  Finished files get the mode the user's umask asks for.  Loading is strict: every
tensor must match the rebuilt module by name and shape.  No pickle is involved.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import re
import tempfile
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from pydantic import ValidationError
from safetensors import SafetensorError, safe_open
from safetensors.torch import load_file, save_model
from torch import nn

from .components import BuildContext, fill_missing_with_zeros
from .deprecations import current_kind
from .errors import CheckpointError, ConfigError, UnknownPluginError, VqtouchError

if TYPE_CHECKING:
    from .plugin_manager import PluginHost


FORMAT_VERSION = "1"
#: The header entry naming the precision a trained component's weights were trained in (``fp32`` or
#: ``bf16``: ``precision: auto`` resolved for the device); a loaded component carries it as
#: ``vqtouch_trained_in`` (None for files written before it was recorded).
TRAINED_IN_KEY = "training.precision"
RESERVED_PREFIXES = ("vqtouch.", "format")


def _json(value: Any) -> str:
    return json.dumps(value, sort_keys=True, separators=(",", ":"))


def _fsync_directory(directory: Path) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:  # some filesystems (and Windows) cannot open folders
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


#: The temporaries of :func:`atomic_write` (``tempfile.mkstemp``: ``.<name>.<8 characters>.tmp``).
TEMPORARY_FILE = re.compile(r"\..+\.[a-z0-9_]{8}\.tmp")
#: The temporary safetensors writes next to the file it is asked for (Rust ``tempfile``:
#: ``.tmp<6 characters>``); in a checkpoint folder it is the full-size leftover of a killed save.
SAFETENSORS_TEMPORARY_FILE = re.compile(r"\.tmp[A-Za-z0-9]{6}")


def _umask() -> int:
    # Read without changing it where possible: os.umask() sets the mask for every thread.
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def atomic_write(path: str | Path, write: Any) -> Path:
    """Call ``write(tmp_path)`` then move the finished file onto ``path`` atomically.

    The file gets mode ``0o666 & ~umask`` like any file the user creates (mkstemp, and
    safetensors' own temporary, would leave it readable by its owner only).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp_name)
    try:
        write(tmp_path)
        os.chmod(tmp_path, 0o666 & ~_umask())
        with open(tmp_path, "rb+") as handle:
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp_path, path)
        _fsync_directory(path.parent)
    except BaseException as exc:
        tmp_path.unlink(missing_ok=True)
        if isinstance(exc, OSError) and exc.filename is None:
            exc.filename = str(path)  # writers (Pillow, safetensors) often raise without naming the file
        raise
    return path


def remove_stale_temporaries(folder: Path, *, safetensors_temporaries: bool = False) -> list[Path]:
    """Delete the leftovers of interrupted :func:`atomic_write` calls in ``folder`` (not below it).

    Only names of atomic_write's pattern are touched, and with ``safetensors_temporaries`` also
    the ``.tmpXXXXXX`` files safetensors writes (pass it only for folders that nothing but
    vqtouch writes to, such as ``checkpoints/step-*``).  Call it only when no other process is
    writing there: a temporary being written looks the same as a stale one.
    """
    removed = []
    try:
        entries = list(folder.iterdir())
    except OSError:
        return removed
    for entry in entries:
        stale = TEMPORARY_FILE.fullmatch(entry.name) or (
            safetensors_temporaries and SAFETENSORS_TEMPORARY_FILE.fullmatch(entry.name)
        )
        if stale and entry.is_file() and not entry.is_symlink():
            try:
                entry.unlink()
            except OSError:
                continue
            removed.append(entry)
    return removed


#: What to do about a write that failed, by errno.
_WRITE_FIXES = {
    errno.ENOSPC: "free disk space and run again",
    errno.EDQUOT: "free disk space and run again",
    errno.EACCES: "make {folder} writable or write elsewhere",
    errno.EPERM: "make {folder} writable or write elsewhere",
    errno.EROFS: "make {folder} writable or write elsewhere",
}


class CheckpointWriteError(CheckpointError):
    """Writing a checkpoint file failed (full disk, read-only folder, ...); nothing was replaced."""

    def __init__(self, path: Path, cause: str, fix: str, kept: str = "nothing was replaced") -> None:
        super().__init__(f"{path}: could not write the checkpoint file: {cause}; {fix} ({kept})")
        self.path, self.cause, self.fix = path, cause, fix

    def keeping(self, kept: str) -> CheckpointWriteError:
        """The same error, saying what the caller kept (e.g. the run's last complete checkpoint)."""
        return CheckpointWriteError(self.path, self.cause, self.fix, kept)


def write_checkpoint_file(path: str | Path, write: Any) -> Path:
    """:func:`atomic_write` for checkpoint files: an OSError or safetensors error while writing
    becomes a one-line :class:`CheckpointWriteError` naming the file, the cause and the fix."""
    path = Path(path)
    try:
        return atomic_write(path, write)
    except OSError as exc:
        cause, code = exc.strerror or _first_line(exc), exc.errno
    except SafetensorError as exc:
        # e.g. "Error while serializing: I/O error: No space left on device (os error 28) at path ..."
        text = _first_line(exc)
        found = re.search(r"I/O error: (.+?) \(os error (\d+)\)", text)
        cause, code = (found.group(1), int(found.group(2))) if found else (text, None)
    fix = _WRITE_FIXES.get(code, "check the disk and run again").format(folder=path.parent)
    raise CheckpointWriteError(path, cause, fix) from None


def checkpoint_metadata(
    component: nn.Module, step: int, host: PluginHost | None = None, extra: Mapping[str, str] | None = None
) -> dict[str, str]:
    """The header metadata for ``component`` (which must have been built by a PluginHost): the
    reserved entries, the plugins' (``vqtouch_checkpoint_metadata``) and the caller's ``extra``
    (e.g. how an adapted tokenizer was made); extra keys are namespaced like a plugin's."""
    spec = getattr(component, "vqtouch_spec", None)
    if spec is None:
        raise CheckpointError(
            f"{type(component).__name__} was not built through vqtouch (no vqtouch_spec); "
            "build components with PluginHost.build so checkpoints can record how to rebuild them"
        )
    config = spec.config.model_dump(mode="json")
    metadata = {
        "format": "pt",
        "vqtouch.format_version": FORMAT_VERSION,
        "vqtouch.component": spec.kind,
        "vqtouch.plugin": spec.config.name,
        "vqtouch.plugin_source": _json(
            {"plugin": spec.source.plugin, "distribution": spec.source.distribution, "version": spec.source.version}
        ),
        "vqtouch.config": _json(config),
        "vqtouch.context": _json(spec.context.model_dump(mode="json")),
        "vqtouch.step": str(int(step)),
    }
    sources = [
        ("a plugin", entries)
        for entries in (
            host.pm.hook.vqtouch_checkpoint_metadata(kind=spec.kind, name=spec.config.name, config=config)
            if host is not None
            else []
        )
    ]
    for who, entries in [*sources, ("the caller", extra)]:
        for key, value in (entries or {}).items():
            if key.startswith(RESERVED_PREFIXES) or not isinstance(value, str):
                raise CheckpointError(
                    f"checkpoint metadata {key!r} from {who} is not allowed: keys must be namespaced (not "
                    "'vqtouch.'/'format') and values must be strings"
                )
            metadata[key] = value
    return metadata


def save(
    component: nn.Module,
    path: str | Path,
    *,
    step: int = 0,
    host: PluginHost | None = None,
    metadata: Mapping[str, str] | None = None,
) -> Path:
    """Write ``component`` to ``path`` (a ``.safetensors`` file) atomically; returns the path.
    ``metadata`` adds namespaced header entries (read back with :func:`read_metadata`).

    A failed write (full disk, ...) raises :class:`CheckpointWriteError`; the file that was at
    ``path`` is untouched.
    """
    path = Path(path)
    if path.suffix != ".safetensors":
        raise CheckpointError(f"{path}: checkpoint files must end in .safetensors")
    metadata = checkpoint_metadata(component, step, host, metadata)
    # safetensors refuses non-contiguous tensors; save_model also de-duplicates tied weights.
    write_checkpoint_file(path, lambda tmp: save_model(component, str(tmp), metadata=metadata))
    return path


def read_metadata(path: str | Path) -> dict[str, str]:
    """The header metadata of a checkpoint, without loading its tensors."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint file")
    try:
        with safe_open(str(path), framework="pt") as handle:
            metadata = handle.metadata() or {}
    except Exception as exc:  # noqa: BLE001 - safetensors raises several error types
        raise CheckpointError(f"{path}: not a readable safetensors checkpoint ({_first_line(exc)})") from None
    if "vqtouch.format_version" not in metadata:
        raise CheckpointError(f"{path}: a safetensors file, but not a vqtouch checkpoint (no vqtouch.* header)")
    if metadata["vqtouch.format_version"] != FORMAT_VERSION:
        raise CheckpointError(
            f"{path}: checkpoint format version {metadata['vqtouch.format_version']!r} is not supported "
            f"by this vqtouch (expects {FORMAT_VERSION!r}); upgrade vqtouch"
        )
    return metadata


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


def files_digest(paths: Iterable[str | Path]) -> str:
    """SHA-256 over the bytes of ``paths``, in order: pins weights a reader depends on (a generator
    records its tokenizer's, and refuses a tokenizer that changed since)."""
    digest = hashlib.sha256()
    for path in paths:
        with open(path, "rb") as handle:
            for block in iter(lambda: handle.read(1 << 20), b""):
                digest.update(block)
    return digest.hexdigest()


def load(path: str | Path, *, host: PluginHost | None = None, map_location: str | torch.device = "cpu") -> nn.Module:
    """Rebuild a component from a checkpoint's header with ``host``'s plugins and load its weights
    strictly.

    Fails with a one-line :class:`CheckpointError` when the file is unreadable, the plugin
    that made it is not installed (naming its distribution), or names/shapes disagree with
    the rebuilt module.  A header written under a 0.1.0 kind name (``encoder``) loads under
    today's (``autoencoder``), with a deprecation warning.  There is no hidden plugin host: leaving
    ``host`` out (as 0.1.0 allowed) is a one-line TypeError that says what to pass.
    """
    if host is None:
        raise TypeError(
            "load() needs host= since vqtouch 0.2.0 (no hidden plugin host): "
            "load(path, host=vqtouch.core.load_plugins())"
        )
    path = Path(path)
    metadata = read_metadata(path)
    kind = current_kind(metadata.get("vqtouch.component", ""))
    plugin = metadata.get("vqtouch.plugin", "")
    try:
        config = json.loads(metadata["vqtouch.config"])
        context = BuildContext.model_validate(json.loads(metadata["vqtouch.context"]))
    except (KeyError, json.JSONDecodeError, ValidationError) as exc:
        raise CheckpointError(f"{path}: damaged vqtouch header ({_first_line(exc)})") from None
    step_text = metadata.get("vqtouch.step", "0")
    if not step_text.isdecimal():
        # Checked before any work: a step that is not a count means the header was edited or damaged.
        raise CheckpointError(
            f"{path}: damaged vqtouch header (vqtouch.step is {step_text!r}, not a step "
            "number); use another checkpoint step, or restore the file from a copy"
        )
    try:
        installed = plugin in host.registry(kind)
    except UnknownPluginError as exc:
        raise CheckpointError(f"{path}: holds a {kind!r} component, which this vqtouch does not know: {exc}") from None
    if not installed:
        try:
            source = json.loads(metadata.get("vqtouch.plugin_source", "{}"))
        except json.JSONDecodeError:
            source = {}
        package = source.get("distribution") or source.get("plugin") or "the plugin that made it"
        version = f" {source['version']}" if source.get("version") else ""
        raise CheckpointError(
            f"{path}: made by {kind} {plugin!r} from {package}{version}, which is not installed "
            f"here; pip install {package}"
        )
    try:
        component = host.build(kind, config, context)
    except ConfigError as exc:
        raise CheckpointError(f"{path}: its stored config no longer validates: {exc}") from None
    except VqtouchError as exc:
        raise CheckpointError(f"{path}: cannot rebuild {kind} {plugin!r}: {exc}") from None
    try:
        tensors = load_file(str(path), device=str(map_location))
    except Exception as exc:  # noqa: BLE001
        raise CheckpointError(f"{path}: tensor data is unreadable ({_first_line(exc)})") from None
    # Refused here, where every reader passes, rather than as constant images or NaN scores later.
    non_finite = [
        name for name, tensor in tensors.items() if tensor.is_floating_point() and not tensor.isfinite().all()
    ]
    if non_finite:
        raise CheckpointError(
            f"{path}: {len(non_finite)} weight tensor(s) hold NaN or Inf (first {non_finite[0]!r}): the training "
            "that wrote it diverged; use an earlier checkpoint (--step) or retrain with a lower learning_rate"
        )
    load_state_strict(component, tensors, path)
    component.vqtouch_step = int(step_text)
    component.vqtouch_trained_in = metadata.get(TRAINED_IN_KEY)
    return component.to(map_location)


def load_state_strict(module: nn.Module, tensors: Mapping[str, torch.Tensor], path: str | Path) -> None:
    """Load ``tensors`` into ``module``: every key present, none extra, every shape equal.

    A module whose state size is learned rather than configured (a fitted clusterer's number of
    families) defines ``resize_to_state(tensors)``; it is called first, and the shapes are then
    checked against the resized module as strictly as any other."""
    resize = getattr(module, "resize_to_state", None)
    if callable(resize):
        resize(tensors)
    expected = module.state_dict()
    # save_model drops tied duplicates; restore them from the kept name.
    tensors = dict(tensors)
    # Paths added later as zero-initialised layers load as zeros from older files (load_missing_as_zeros).
    fill_missing_with_zeros(module, tensors)
    for name, value in expected.items():
        if name not in tensors:
            for other_name, other_value in expected.items():
                if other_name in tensors and other_value.data_ptr() == value.data_ptr() and value.numel():
                    tensors[name] = tensors[other_name]
                    break
    missing = sorted(set(expected) - set(tensors))
    unexpected = sorted(set(tensors) - set(expected))
    if missing or unexpected:
        parts = []
        if missing:
            parts.append(f"missing {len(missing)} tensor(s), first {missing[0]!r}")
        if unexpected:
            parts.append(f"unexpected {len(unexpected)} tensor(s), first {unexpected[0]!r}")
        raise CheckpointError(f"{path}: does not fit the rebuilt model: " + "; ".join(parts))
    for name, value in expected.items():
        if tuple(tensors[name].shape) != tuple(value.shape):
            raise CheckpointError(
                f"{path}: tensor {name!r} has shape {tuple(tensors[name].shape)} in the file but "
                f"{tuple(value.shape)} in the model built from its config"
            )
    module.load_state_dict(tensors, strict=True)


#: ``pretrained:NAME`` names bundled weights wherever a run or a tokenizer is asked for
#: (``--run pretrained:tour``); a plugin that ships bundles opens them (``vqtouch_open_pretrained``).
PRETRAINED_PREFIX = "pretrained:"


def is_pretrained(spec: Any) -> bool:
    """Whether ``spec`` names bundled weights (``pretrained:NAME``) rather than a folder."""
    return isinstance(spec, str) and spec.startswith(PRETRAINED_PREFIX)


def open_pretrained(
    spec: str, host: PluginHost, device: str | torch.device = "cpu", *, tokenizer_only: bool = False
) -> Any:
    """The bundle ``spec`` (``pretrained:NAME``) names, opened on ``device`` by the plugin that ships it:
    an object with ``tokenizer``, ``generator``, ``conditioners``, ``run_config`` and ``folder`` (see
    :func:`vqtouch.core.hookspecs.vqtouch_open_pretrained`; ``tokenizer_only`` builds the tokenizer alone).
    One-line ConfigError when no plugin has it."""
    name = spec[len(PRETRAINED_PREFIX) :]
    bundle = host.pm.hook.vqtouch_open_pretrained(name=name, host=host, device=device, tokenizer_only=tokenizer_only)
    if bundle is None:
        raise ConfigError(
            f"{spec}: no installed plugin ships bundled weights (the built-in 'pretrained' plugin may "
            "be blocked by VQTOUCH_BLOCK_PLUGINS)"
        )
    return bundle

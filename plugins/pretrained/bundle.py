"""Bundled checkpoints: write a trained generator run (and its tokenizer), or a tokenizer run alone,
into the package, read it back.

A bundle is a folder ``weights/<name>/`` inside this package::

    tokenizer/autoencoder.safetensors  tokenizer/quantizer.safetensors
    generator/generator.safetensors    generator/conditioner_<i>.safetensors   (absent: a tokenizer bundle)

A tokenizer bundle serves every command that reads a tokenizer (``--tokenizer pretrained:NAME``,
``evaluate reconstruction --run pretrained:NAME``, ``adapt``); what needs a generator refuses it in one
line.  When the run was trained from a recipe shipped in :data:`RECIPES` (``--config`` one of its files),
``pretrained.recipe`` names that file.

Every file is an ordinary vqtouch checkpoint (:func:`vqtouch.core.save`: the component's config,
build context and training step in its header, loaded strictly) plus three header entries that
say where it came from: ``pretrained.command`` (the ``vqtouch`` command line that trained it, from
the run's env.json), ``pretrained.run_config`` (the training run's whole config) and
``pretrained.stored_as`` (the precision of the stored parameters); the generator's files also
record ``pretrained.weights`` (``ema``: the moving average training kept, or ``raw``).  The header is the one source
of truth: nothing else describes a bundle.

To keep the package small, parameters are stored in float16 except the quantizer's, whose
codebook decides which code each latent gets (quantizer maths stays fp32); loading casts them
back to the module's float32.  The scores the ``pretrained`` stage reports are those of the
weights as stored.
"""

from __future__ import annotations

import copy
import json
from dataclasses import dataclass
from pathlib import Path
from collections.abc import Mapping
from typing import Any

import torch
from torch import nn

from vqtouch.core import ConfigError, PluginHost, load, read_metadata, save
from vqtouch.plugins.runtime.run_dir import RunDir
from vqtouch.core.checkpoint import TRAINED_IN_KEY
from vqtouch.plugins.runtime.outputs import staged_output
from vqtouch.plugins.tokenizer import Tokenizer

#: Where the bundles live inside the installed package.
BUNDLES = Path(__file__).parent / "weights"
TOKENIZER = "tokenizer"
GENERATOR = "generator"
COMMAND_KEY = "pretrained.command"
RUN_CONFIG_KEY = "pretrained.run_config"
STORED_KEY = "pretrained.stored_as"
#: Which of the run's weights the generator files hold: ``ema`` (the moving average) or ``raw``.
WEIGHTS_KEY = "pretrained.weights"
#: The shipped recipe file (a name in :data:`RECIPES`) the run was trained from, when it was.
RECIPE_KEY = "pretrained.recipe"
#: The shipped training recipes: config files ``vqtouch train ... --config RECIPE`` reproduces a bundle with.
RECIPES = Path(__file__).parent / "recipes"
#: fp16's largest finite value: a parameter beyond it cannot be stored in half precision.
FP16_MAX = 65504.0


def is_bundle_folder(folder: Path) -> bool:
    """Whether ``folder`` holds a bundle: a tokenizer, with or without a generator."""
    return (folder / TOKENIZER / "autoencoder.safetensors").is_file()


def has_generator(folder: Path) -> bool:
    """Whether the bundle in ``folder`` holds a generator (else it is a tokenizer bundle)."""
    return (folder / GENERATOR / "generator.safetensors").is_file()


def bundle_names(root: Path | None = None) -> list[str]:
    """The bundles present under ``root`` (default: the package's), sorted."""
    root = root or BUNDLES
    if not root.is_dir():
        return []
    # Hidden folders are exports in progress (or killed half-way), never bundles.
    return sorted(path.name for path in root.iterdir() if not path.name.startswith(".") and is_bundle_folder(path))


def bundle_folder(name: str, root: Path | None = None) -> Path:
    """The folder of bundle ``name``; a one-line error listing the bundles when there is none of that name."""
    root = root or BUNDLES
    names = bundle_names(root)
    if name not in names:
        raise ConfigError(
            f"no bundled checkpoints named {name!r} in {root}; bundled: {', '.join(names) or 'none'} "
            "(make one with `vqtouch pretrained export --run RUN --name NAME`)"
        )
    return root / name


def half_precision_copy(module: nn.Module, where: str) -> nn.Module:
    """A copy of ``module`` whose floating-point parameters are float16 (buffers untouched); refuses
    a parameter fp16 cannot hold rather than storing infinities."""
    copied = copy.deepcopy(module)
    for name, parameter in copied.named_parameters():
        if not parameter.is_floating_point():
            continue
        largest = parameter.detach().abs().max().item() if parameter.numel() else 0.0
        if not largest < FP16_MAX:
            raise ConfigError(
                f"{where}: parameter {name!r} reaches {largest:.3g}, beyond float16's {FP16_MAX:g}; "
                "export with --precision fp32"
            )
        parameter.data = parameter.data.half()
    return copied


def _provenance(run: RunDir) -> dict[str, str]:
    """The header entries naming how ``run`` was trained: its command line and its config."""
    env = json.loads((run.path / "env.json").read_text()) if (run.path / "env.json").is_file() else {}
    argv = env.get("argv") or ["(unknown command)"]
    command = " ".join(argv)
    facts = [f"vqtouch git {env['git_revision'][:12]}"] if env.get("git_revision") else []
    if env.get("device_name") not in (None, "cpu"):
        facts.append(f"on {env['device_name']}")  # a GPU's minutes are not a CPU's: say which trained it
    if facts:
        command += "  # " + " ".join(facts)
    headers = {COMMAND_KEY: command, RUN_CONFIG_KEY: (run.path / "config.json").read_text()}
    recipe = shipped_recipe(argv)
    return headers | ({RECIPE_KEY: recipe} if recipe else {})


def shipped_recipe(argv: list[str]) -> str | None:
    """The name of the shipped recipe (a file of :data:`RECIPES`) a command line trained from, if any."""
    for flag, value in zip(argv, argv[1:]):
        path = Path(value)
        if flag == "--config" and path.parent.resolve() == RECIPES.resolve() and path.is_file():
            return path.name
    return None


#: The generator options a bundle may set for itself at export (``vqtouch pretrained export --sampling``).
SAMPLING_DEFAULTS = ("steps", "guidance", "conditioner_guidance", "truncation")
SAMPLING_KEY = "pretrained.sampling_defaults"


def _sampling_defaults(run_config_text: str, sampling: dict[str, Any], host: PluginHost) -> dict[str, str]:
    """The header entries of a bundle whose sampling defaults replace its run's: the run config with
    them set (validated like any config: a bad value is a one-line ConfigError) and the overrides."""
    from vqtouch.core import validate_experiment

    unknown = sorted(set(sampling) - set(SAMPLING_DEFAULTS))
    if unknown:
        raise ConfigError(
            f"--sampling {unknown[0]}: a bundle sets only its sampling defaults ({', '.join(SAMPLING_DEFAULTS)})"
        )
    config = json.loads(run_config_text)
    config["generator"] = {**config["generator"], **sampling}
    validate_experiment(config, host)
    return {RUN_CONFIG_KEY: json.dumps(config, indent=2) + "\n", SAMPLING_KEY: json.dumps(sampling, sort_keys=True)}


def export_bundle(
    run: str | Path,
    name: str,
    host: PluginHost,
    *,
    root: Path | None = None,
    precision: str = "fp16",
    overwrite: bool = False,
    sampling: Mapping[str, Any] | None = None,
    weights: str | None = None,
) -> Path:
    """Write the newest checkpoint of ``run`` as bundle ``name`` under ``root``; returns the bundle's
    folder.  A run whose generator stage trained gives its generator, conditioners and the tokenizer it
    was trained on; a tokenizer run (``vqtouch train tokenizer``) gives a tokenizer bundle.

    ``sampling``: the bundle's own sampling defaults, replacing the run's (keys of
    :data:`SAMPLING_DEFAULTS`, e.g. ``{"conditioner_guidance": {"label": 2}}``): how to sample is
    chosen after training, when it can be measured.  They go into the recorded run config and, as
    given, into ``pretrained.sampling_defaults``, so the headers say what was changed.

    ``weights``: ``"ema"`` or ``"raw"``, which of the run's weights the bundle holds (None: the ones the
    run samples with by default, its EMA when it kept one); recorded in ``pretrained.weights``."""
    if precision not in ("fp16", "fp32"):
        raise ConfigError(f"--precision {precision!r}: choose fp16 or fp32")
    if not name or any(char in name for char in "/\\ ") or name.startswith("."):
        raise ConfigError(f"bundle name {name!r}: use a plain folder name such as 'tour'")
    folder = (root or BUNDLES) / name
    if folder.exists() and not overwrite:
        raise ConfigError(f"{folder} exists; pass --overwrite to replace bundle {name!r}")
    from vqtouch.plugins.generator import GENERATOR_CHECKPOINTS

    run_dir = RunDir.open(run)
    if not (run_dir.checkpoints / GENERATOR_CHECKPOINTS).is_dir():
        if sampling or weights:
            raise ConfigError(
                f"{run} trained no generator: a tokenizer bundle has no sampling defaults or generator weights "
                "(drop --sampling and --weights)"
            )
        return _export_tokenizer_bundle(run_dir, folder, host, precision=precision, overwrite=overwrite)
    return _export_generator_bundle(
        run, folder, host, precision=precision, overwrite=overwrite, sampling=sampling, weights=weights
    )


def _store(module: nn.Module, path: Path, headers: dict[str, str], host: PluginHost, half: bool) -> None:
    """Save ``module`` at ``path`` with the bundle ``headers``, its parameters in float16 when ``half``."""
    if getattr(module, "vqtouch_trained_in", None):
        headers = headers | {TRAINED_IN_KEY: module.vqtouch_trained_in}
    stored = half_precision_copy(module, str(path)) if half else module
    save(
        stored,
        path,
        step=getattr(module, "vqtouch_step", 0),
        host=host,
        metadata={**headers, STORED_KEY: "float16 parameters" if half else "float32"},
    )


def _store_tokenizer(
    tokenizer: Tokenizer, partial: Path, headers: dict[str, str], host: PluginHost, half: bool
) -> None:
    (partial / TOKENIZER).mkdir()
    _store(tokenizer.autoencoder, partial / TOKENIZER / "autoencoder.safetensors", headers, host, half)
    # The quantizer stays float32: its codebook decides which code each latent gets.
    _store(tokenizer.quantizer, partial / TOKENIZER / "quantizer.safetensors", headers, host, False)


# Staged beside the bundle and moved into place whole (as every command's --out): a failed or
# interrupted export leaves no partial bundle to block the retry, and --overwrite keeps the old bundle
# until the new one is complete.  Bundles live inside the package on purpose; --overwrite replaces only a bundle.
def _export_tokenizer_bundle(run: RunDir, folder: Path, host: PluginHost, *, precision: str, overwrite: bool) -> Path:
    from vqtouch.plugins.tokenizer import load_tokenizer

    tokenizer, _ = load_tokenizer(run, host)
    with staged_output(folder, overwrite=overwrite, into_package=True, recognise=is_bundle_folder) as partial:
        _store_tokenizer(tokenizer, partial, _provenance(run), host, precision == "fp16")
    return folder


def _export_generator_bundle(
    generator_run: str | Path,
    folder: Path,
    host: PluginHost,
    *,
    precision: str,
    overwrite: bool,
    sampling: Mapping[str, Any] | None,
    weights: str | None,
) -> Path:
    from vqtouch.plugins.generator import generator_tokenizer, load_pipeline

    pipe = load_pipeline(generator_run, host=host, device="cpu", weights=weights)
    if pipe.sensor_tag is not None:
        raise ConfigError(
            f"{generator_run}: a sensor-tagged generator (vqtouch fewshot) cannot be bundled yet; "
            "share its run folder instead"
        )
    run = RunDir.open(generator_run)
    section = run.load_config(host).generator
    source = generator_tokenizer(run, section)
    if (
        isinstance(source, Path)
        and source.parent.name == "checkpoints"
        and (source.parent.parent / "config.json").is_file()
    ):
        source = RunDir.open(source.parent.parent)  # a step folder of a run: that run's provenance
    generator_headers = _provenance(run)
    if sampling:
        generator_headers |= _sampling_defaults(generator_headers[RUN_CONFIG_KEY], dict(sampling), host)
    if isinstance(source, RunDir):
        tokenizer_headers = _provenance(source)
    else:
        # A tokenizer checkpoint folder (an adapted tokenizer, or an earlier bundle's tokenizer): keep the
        # provenance its own headers record, else the generator run's.
        recorded = read_metadata(source / "autoencoder.safetensors")
        tokenizer_headers = {
            key: recorded[key] for key in (COMMAND_KEY, RUN_CONFIG_KEY, RECIPE_KEY) if key in recorded
        } or generator_headers
    half = precision == "fp16"
    with staged_output(folder, overwrite=overwrite, into_package=True, recognise=is_bundle_folder) as partial:
        _store_tokenizer(pipe.tokenizer, partial, tokenizer_headers, host, half)
        (partial / GENERATOR).mkdir()
        # The weights the run samples with by default (its EMA when it kept one), and which they are.
        generator_headers = generator_headers | {WEIGHTS_KEY: pipe.settings["weights"]}
        _store(pipe.generator, partial / GENERATOR / "generator.safetensors", generator_headers, host, half)
        for index, conditioner in enumerate(pipe.conditioners):
            _store(conditioner, partial / GENERATOR / f"conditioner_{index}.safetensors", generator_headers, host, half)
    return folder


@dataclass
class Bundle:
    """A loaded bundle: the tokenizer, the generator and its conditioners, and where they came from."""

    name: str
    folder: Path
    tokenizer: Any
    #: None when opened with ``tokenizer_only``.
    generator: nn.Module | None
    conditioners: list[nn.Module]
    tokenizer_step: int
    generator_step: int
    tokenizer_command: str
    generator_command: str
    run_config: dict[str, Any]
    #: ``ema`` or ``raw``: which of the run's weights the generator files hold (``raw`` for bundles
    #: exported before vqtouch recorded it).
    weights: str = "raw"

    @property
    def tokenizer_folder(self) -> Path:
        """The folder of the tokenizer's files (a tokenizer checkpoint folder, read-only)."""
        return self.folder / TOKENIZER

    @property
    def conditioner_names(self) -> list[str]:
        """The registered name of each conditioner, in the generator's order."""
        return [conditioner.vqtouch_spec.config.name for conditioner in self.conditioners]

    @property
    def size_bytes(self) -> int:
        """The bundle's size on disk."""
        return sum(path.stat().st_size for path in self.folder.rglob("*.safetensors"))


def describe_bundle(folder: Path) -> dict[str, Any]:
    """A bundle's facts from its headers alone (no tensors loaded): steps, commands, recipes, files and
    sizes (the generator's entries None for a tokenizer bundle)."""
    tokenizer = read_metadata(folder / TOKENIZER / "autoencoder.safetensors")
    generator = read_metadata(folder / GENERATOR / "generator.safetensors") if has_generator(folder) else None
    files = sorted(folder.rglob("*.safetensors"))
    conditioners = [
        json.loads(read_metadata(path)["vqtouch.config"])["name"]
        for path in sorted(
            (folder / GENERATOR).glob("conditioner_*.safetensors"), key=lambda p: int(p.stem.split("_")[1])
        )
    ]
    facts = generator if generator is not None else tokenizer
    return {
        "name": folder.name,
        "kind": "generator" if generator is not None else "tokenizer",
        "tokenizer_step": int(tokenizer["vqtouch.step"]),
        "generator_step": int(generator["vqtouch.step"]) if generator is not None else None,
        "tokenizer": json.loads(tokenizer["vqtouch.config"])["name"],
        "conditioners": conditioners,
        "tokenizer_command": tokenizer.get(COMMAND_KEY, "?"),
        "generator_command": generator.get(COMMAND_KEY, "?") if generator is not None else None,
        "recipes": {
            "tokenizer": tokenizer.get(RECIPE_KEY),
            "generator": generator.get(RECIPE_KEY) if generator is not None else None,
        },
        "stored_as": facts.get(STORED_KEY, "?"),
        "trained_in": {
            "tokenizer": tokenizer.get(TRAINED_IN_KEY),
            "generator": generator.get(TRAINED_IN_KEY) if generator is not None else None,
        },
        "weights": generator.get(WEIGHTS_KEY, "raw") if generator is not None else None,
        "sampling_defaults": json.loads(generator.get(SAMPLING_KEY, "{}")) if generator is not None else {},
        "files": len(files),
        "megabytes": round(sum(path.stat().st_size for path in files) / 1e6, 2),
    }


def load_bundle(
    name: str,
    host: PluginHost,
    *,
    device: str | torch.device = "cpu",
    root: Path | None = None,
    tokenizer_only: bool = False,
) -> Bundle:
    """Load bundle ``name`` strictly (every tensor by name and shape) onto ``device``, in eval mode;
    ``tokenizer_only``: the tokenizer alone (no generator, no conditioners built)."""

    folder = bundle_folder(name, root)
    if not tokenizer_only and not has_generator(folder):
        raise ConfigError(
            f"pretrained:{name} is a tokenizer bundle (no generator): use it where a tokenizer is read, e.g. "
            f"`vqtouch train generator --tokenizer pretrained:{name}` or `vqtouch evaluate reconstruction "
            f"--run pretrained:{name}`"
        )
    autoencoder = load(folder / TOKENIZER / "autoencoder.safetensors", host=host, map_location=device)
    quantizer = load(folder / TOKENIZER / "quantizer.safetensors", host=host, map_location=device)
    generator, conditioners = None, []
    if not tokenizer_only:
        generator = load(folder / GENERATOR / "generator.safetensors", host=host, map_location=device).eval()
        paths = sorted((folder / GENERATOR).glob("conditioner_*.safetensors"), key=lambda p: int(p.stem.split("_")[1]))
        conditioners = [load(path, host=host, map_location=device).eval() for path in paths]
    tokenizer_headers = read_metadata(folder / TOKENIZER / "autoencoder.safetensors")
    headers = read_metadata(folder / GENERATOR / "generator.safetensors") if has_generator(folder) else {}
    return Bundle(
        name=name,
        folder=folder,
        tokenizer=Tokenizer(autoencoder, quantizer).eval(),
        generator=generator,
        conditioners=conditioners,
        tokenizer_step=autoencoder.vqtouch_step,
        generator_step=int(headers["vqtouch.step"]) if headers else 0,
        tokenizer_command=tokenizer_headers.get(COMMAND_KEY, "?"),
        generator_command=headers.get(COMMAND_KEY, "?"),
        run_config=json.loads((headers or tokenizer_headers).get(RUN_CONFIG_KEY, "{}")),
        weights=headers.get(WEIGHTS_KEY, "raw"),
    )

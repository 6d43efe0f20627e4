"""Hook specifications: the whole plugin API of vqtouch.

A plugin is a module (or object) with functions decorated by ``vqtouch.core.hookimpl``
whose names match the specs below.  Only names starting with ``vqtouch_`` are treated as
hooks, and a misspelled one fails loudly when plugins load (pluggy ``check_pending``).

Registration hooks receive a ``register`` callback::

    @hookimpl
    def vqtouch_register_conditioners(register):
        register("label", build_label_conditioner, LabelConditionerConfig,
                 description="Learned embedding per class label.")

``register(name, factory, config, *, description="", aliases=(), inputs=(), demo=None, optional_inputs=())``:
``config`` is the plugin's :class:`~vqtouch.core.PluginConfig` subclass (with
``name: Literal[name]``) and ``factory(config, context, **inputs)`` builds the component from a
validated config and a :class:`~vqtouch.core.BuildContext`.  ``inputs`` names built
components the factory needs (``("sensor",)`` for a dataset that renders with the
experiment's sensor); the assembly supplies them.  ``optional_inputs`` names components the
factory takes only when the experiment has them (``("paired_sensor",)``: a dataset that renders
the same contact with a second sensor); absent ones are not passed.  ``demo`` caps options for
``vqtouch demo`` (e.g. ``{"num_samples": 240}``).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import pluggy

from .errors import VqtouchDeprecationWarning

if TYPE_CHECKING:
    from .plugin_manager import PluginHost
    from .config import ExperimentConfig


PROJECT_NAME = "vqtouch"

hookspec = pluggy.HookspecMarker(PROJECT_NAME)
hookimpl = pluggy.HookimplMarker(PROJECT_NAME)

Register = Callable[..., None]


@hookspec
def vqtouch_register_autoencoders(register: Register) -> None:
    """Register tokenizer autoencoders (``vqtouch.core.Autoencoder`` subclasses), e.g. ``vqgan``."""


@hookspec(
    warn_on_impl=VqtouchDeprecationWarning(
        "hook 'vqtouch_register_encoders' was renamed to 'vqtouch_register_autoencoders' in vqtouch 0.2.0; rename the "
        "function ('vqtouch_register_encoders' stops working in 0.3.0)"
    )
)
def vqtouch_register_encoders(register: Register) -> None:
    """Deprecated 0.1.0 name of :func:`vqtouch_register_autoencoders` (its registrations still count)."""


@hookspec
def vqtouch_register_quantizers(register: Register) -> None:
    """Register quantizers (``vqtouch.core.Quantizer`` subclasses), e.g. ``vq``, ``ema_vq``."""


@hookspec
def vqtouch_register_discriminators(register: Register) -> None:
    """Register GAN discriminators for tokenizer training (``vqtouch.core.Discriminator``), e.g. ``patchgan``."""


@hookspec
def vqtouch_register_conditioners(register: Register) -> None:
    """Register conditioners (``vqtouch.core.Conditioner`` subclasses): label, visual, tactile, text."""


@hookspec
def vqtouch_register_sensor_families(register: Register) -> None:
    """Register sensor families (``vqtouch.core.SensorFamily`` subclasses) that render tactile images."""


@hookspec
def vqtouch_register_generators(register: Register) -> None:
    """Register generators over code grids (``vqtouch.core.Generator`` subclasses)."""


@hookspec
def vqtouch_register_samplers(register: Register) -> None:
    """Register samplers of discrete-diffusion generators (``vqtouch.core.Sampler`` subclasses)."""


@hookspec
def vqtouch_register_best_of_rankers(register: Register) -> None:
    """Register best-of-K rankers (``vqtouch.core.BestOfRanker`` subclasses): what keeps one of several
    candidates drawn per condition (``--best-of-rank NAME``)."""


@hookspec
def vqtouch_register_clusterers(register: Register) -> None:
    """Register clusterers that group sensors into families (``vqtouch.core.Clusterer``)."""


@hookspec
def vqtouch_register_datasets(register: Register) -> None:
    """Register dataset readers (``vqtouch.core.TactileDataset`` subclasses)."""


@hookspec
def vqtouch_register_metrics(register: Register) -> None:
    """Register image metrics (``vqtouch.core.Metric`` subclasses)."""


@hookspec
def vqtouch_register_scenes(register: Callable[..., None]) -> None:
    """Register scene presets: ``register(name, config, *, description="")``.

    ``config`` is a partial experiment configuration (a nested dict) that selects the
    stages the scene runs and the plugin for each slot it needs; the user's files and
    ``--set`` overrides are merged on top.
    """


@hookspec
def vqtouch_add_commands(subparsers: argparse._SubParsersAction) -> None:
    """Add CLI subcommands.

    Each added parser must set a handler with ``parser.set_defaults(handler=fn)``; ``fn``
    receives the parsed ``argparse.Namespace`` and returns the exit status.
    """


@hookspec
def vqtouch_register_stages(register: Callable[..., None]) -> None:
    """Register pipeline stages: ``register(name, run, *, section=None, needs=(), uses=(),
    description="", demo=None, makes=(), trains=None)``.

    ``run(job: vqtouch.core.StageJob) -> dict | None`` does the stage's work; ``section`` is the
    stage's own config model (validated at ``config.<name>``); ``needs``/``uses`` are the slot
    paths it requires / uses when set; ``demo`` caps section options for the demo; ``makes`` the
    products it publishes in its run for later stages (``job.publish``, ``job.product``);
    ``trains`` the section option holding how long it trains (one of ``demo``'s keys), so the
    demo's report can say a model trained that briefly.  See :mod:`vqtouch.core.stages`.
    """


@hookspec
def vqtouch_validate_experiment(config: ExperimentConfig) -> None:
    """Reject impossible plugin combinations by raising ``vqtouch.core.ConfigError``.

    Called once for every resolved experiment configuration, after each slot validated.
    """


@hookspec
def vqtouch_checkpoint_metadata(kind: str, name: str, config: dict[str, Any]) -> dict[str, str] | None:
    """Return extra string metadata for a checkpoint header.

    Keys must be namespaced with the plugin's name (``"myplugin.calibration_id"``); the
    ``vqtouch.`` and ``format`` keys are reserved.
    """


@hookspec(firstresult=True)
def vqtouch_open_pretrained(name: str, host: PluginHost, device: Any, tokenizer_only: bool) -> Any:
    """Open the bundled pretrained weights ``name`` (what ``--run pretrained:NAME`` names), or return
    None when this plugin ships none.

    The answer has the attributes ``tokenizer``, ``generator``, ``conditioners`` (built, in eval mode,
    on ``device``; with ``tokenizer_only`` the generator is None and the conditioners empty, so nothing
    else is built), ``run_config`` (the config dict of the run that trained them), ``folder`` and
    ``tokenizer_folder`` (the tokenizer's checkpoint folder, what ``--tokenizer pretrained:NAME`` trains on).  The
    first plugin that answers wins; a plugin that knows the name but cannot open it raises a one-line
    ``vqtouch.core.ConfigError``.  Through this hook the generation pipeline opens bundles without
    importing the package that ships them.
    """

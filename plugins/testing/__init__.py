"""Contract checks for plugin authors: the checks every built-in plugin passes, for your own.

Call :func:`check_plugin` from your package's pytest suite to check one registered plugin
against the contract of its kind, exactly as vqtouch's own test suite checks the built-ins::

    from vqtouch.core import load_plugins
    from vqtouch.plugins.testing import check_plugin

    def test_my_sensor_meets_the_vqtouch_contract(tmp_path):
        host = load_plugins(autoload=False, extra=["my_package.vqtouch_plugin"])
        check_plugin(host, "sensor_family", "my_sensor", tmp_dir=tmp_path)

    def test_my_conditioner_meets_the_vqtouch_contract(tmp_path):
        host = load_plugins(autoload=False, extra=["my_package.vqtouch_plugin"])
        check_plugin(host, "conditioner", "my_conditioner", options={"width": 8}, tmp_dir=tmp_path)

A failed check raises :class:`AssertionError` whose message names the plugin and what is
wrong, so pytest reports it like any failed ``assert``.  What is checked:

- for every kind, the registration contract (:func:`check_registration`): a strict, frozen,
  documented options model whose ``name`` is ``Literal[<registered name>]`` and whose options
  all have defaults, a description, ``demo`` caps that name real options;
- the component is built from ``options`` (tiny ones keep the checks fast) in ``context`` and
  is an instance of its kind's base class from :mod:`vqtouch.core.components`;
- the behaviour of that base class: :func:`check_sensor_family`, :func:`check_conditioner`,
  :func:`check_autoencoder`, :func:`check_quantizer`, :func:`check_discriminator`,
  :func:`check_clusterer`, :func:`check_metric`, :func:`check_dataset`, :func:`check_generator`,
  :func:`check_sampler`, :func:`check_best_of_ranker`;
- for every ``nn.Module`` kind, the checkpoint round trip (:func:`check_round_trip`): saved
  with :func:`vqtouch.core.save` and rebuilt with :func:`vqtouch.core.load`, the component
  has the same state and computes the same outputs on fixed inputs.

The checks dispatch on the kind's base class, never on plugin names.  A plugin whose build
needs a pretrained file that is not present (:class:`~vqtouch.core.MissingWeightsError`) is
skipped under pytest with the error's message, which names the file; pass
``missing_weights="raise"`` to fail instead.  Each ``check_*`` function can also be called
on its own with a component you built.
"""

from __future__ import annotations
from ._support import DEFAULT_CONTEXT, SAMPLE_KEYS
from .data import check_clusterer, check_dataset, check_metric
from .models import (
    check_autoencoder,
    check_conditioner,
    check_discriminator,
    check_generator,
    check_quantizer,
    check_sampler,
    check_sensor_family,
    example_condition,
    press_height_maps,
    schedule_from_host,
)
from .rankers import check_best_of_ranker
from .registration import build_for_check, check_plugin, check_registration
from .round_trip import check_round_trip, probe_outputs

__all__ = [
    "DEFAULT_CONTEXT",
    "SAMPLE_KEYS",
    "build_for_check",
    "check_autoencoder",
    "check_clusterer",
    "check_conditioner",
    "check_dataset",
    "check_discriminator",
    "check_generator",
    "check_metric",
    "check_plugin",
    "check_quantizer",
    "check_registration",
    "check_sampler",
    "check_best_of_ranker",
    "schedule_from_host",
    "check_round_trip",
    "check_sensor_family",
    "example_condition",
    "press_height_maps",
    "probe_outputs",
]

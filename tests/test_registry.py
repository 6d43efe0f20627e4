from typing import Literal

import pytest
from pydantic import Field, ValidationError

from vqtouch.core import PluginConfig, PluginError, UnknownPluginError
from vqtouch.core.registry import PluginEntry, PluginSource, Registry


class AlphaConfig(PluginConfig):
    name: Literal["alpha"] = "alpha"
    width: int = Field(8, gt=0)


class BetaConfig(PluginConfig):
    name: Literal["beta"] = "beta"


SOURCE_A = PluginSource("plug_a", "plug_a", "pkg-a", "1.0")
SOURCE_B = PluginSource("plug_b", "plug_b", "pkg-b", "2.0")


def make_registry() -> Registry:
    registry = Registry("autoencoder", "test autoencoders")
    registry.add(PluginEntry("autoencoder", "alpha", lambda c, x: None, AlphaConfig, "", SOURCE_A, aliases=("a",)))
    registry.add(PluginEntry("autoencoder", "beta", lambda c, x: None, BetaConfig, "", SOURCE_A))
    return registry


def test_duplicate_name_names_both_sources():
    registry = make_registry()
    with pytest.raises(PluginError) as info:
        registry.add(PluginEntry("autoencoder", "alpha", lambda c, x: None, AlphaConfig, "", SOURCE_B))
    message = str(info.value)
    assert "duplicate autoencoder name 'alpha'" in message
    assert "plug_a" in message and "pkg-a" in message and "plug_b" in message and "pkg-b" in message


def test_duplicate_alias_is_rejected():
    registry = make_registry()

    class GammaConfig(PluginConfig):
        name: Literal["gamma"] = "gamma"

    with pytest.raises(PluginError, match="duplicate autoencoder name 'a'"):
        registry.add(PluginEntry("autoencoder", "gamma", lambda c, x: None, GammaConfig, "", SOURCE_B, aliases=("a",)))


def test_unknown_name_lists_available_and_closest():
    with pytest.raises(UnknownPluginError) as info:
        make_registry().get("alpah")
    assert str(info.value) == "unknown autoencoder 'alpah'; available: alpha, beta; did you mean 'alpha'?"


def test_alias_resolves_to_canonical_entry():
    registry = make_registry()
    assert registry.get("a").name == "alpha"
    assert registry.validate_config({"name": "a"}).name == "alpha"


def test_config_name_must_match_registered_name():
    registry = Registry("autoencoder", "x")
    with pytest.raises(PluginError, match=r"declares name 'alpha'.*Literal\['other'\]"):
        registry.add(PluginEntry("autoencoder", "other", lambda c, x: None, AlphaConfig, "", SOURCE_A))


def test_config_must_be_plugin_config_subclass():
    registry = Registry("autoencoder", "x")
    with pytest.raises(PluginError, match="subclass of vqtouch.core.PluginConfig"):
        registry.add(PluginEntry("autoencoder", "alpha", lambda c, x: None, dict, "", SOURCE_A))


def test_frozen_registry_refuses_registration():
    registry = make_registry()
    registry.freeze()

    class GammaConfig(PluginConfig):
        name: Literal["gamma"] = "gamma"

    with pytest.raises(PluginError, match="frozen"):
        registry.add(PluginEntry("autoencoder", "gamma", lambda c, x: None, GammaConfig, "", SOURCE_A))


def test_validate_config_uses_the_plugin_model():
    registry = make_registry()
    assert registry.validate_config({"name": "alpha", "width": 3}) == AlphaConfig(width=3)
    assert registry.validate_config("beta") == BetaConfig()
    with pytest.raises(ValidationError, match="greater than 0"):
        registry.validate_config({"name": "alpha", "width": 0})
    with pytest.raises(ValidationError, match="unknown option 'depth'"):
        registry.validate_config({"name": "beta", "depth": 1})
    with pytest.raises(UnknownPluginError, match="needs a 'name' key"):
        registry.validate_config({"width": 1})


def test_single_entry_registry_validates_without_union():
    registry = Registry("autoencoder", "x")
    registry.add(PluginEntry("autoencoder", "alpha", lambda c, x: None, AlphaConfig, "", SOURCE_A))
    assert registry.validate_config({"name": "alpha"}).width == 8


def test_empty_registry_says_none_installed():
    with pytest.raises(UnknownPluginError, match=r"available: \(none installed\)"):
        Registry("generator", "x").get("vq_diffusion")

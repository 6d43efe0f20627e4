"""`vqtouch generate --conditioner INDEX|NAME`: which conditioner encodes the condition when several
read the same sample key; never silently the first."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from vqtouch.core import ConfigError
from vqtouch.plugins.generator.pipeline import GenerationPipeline


def _pipeline(*conditioners: tuple[str, str]) -> GenerationPipeline:
    """A pipeline holding conditioners (name, sample_key); only the conditioner lookup is exercised."""
    modules = [SimpleNamespace(sample_key=key) for _, key in conditioners]
    config = SimpleNamespace(generator=SimpleNamespace(conditioners=[SimpleNamespace(name=n) for n, _ in conditioners]))
    return GenerationPipeline(None, None, modules, None, "posterior", {}, [], 64, None, None, None, config)


def test_one_conditioner_per_key_needs_no_choice():
    pipe = _pipeline(("label", "label"), ("visual", "visual"), ("tactile", "tactile_source"))
    assert pipe.conditioner_index("visual") == 1
    assert pipe.conditioner_index("tactile") == 2  # a tactile condition is the paired sensor's image
    assert pipe.conditioner_names() == ["0:label", "1:visual", "2:tactile"]


def test_two_conditioners_on_one_key_must_be_chosen_by_index_or_name():
    pipe = _pipeline(("label", "label"), ("clip", "visual"), ("visual", "visual"))
    with pytest.raises(
        ConfigError,
        match=r"2 conditioners reading 'visual' \(1:clip, 2:visual\); choose one with "
        r"--conditioner INDEX\|NAME",
    ):
        pipe.conditioner_index("visual")
    assert pipe.conditioner_index("visual", "clip") == 1
    assert pipe.conditioner_index("visual", "visual") == 2
    assert pipe.conditioner_index("visual", 2) == 2 and pipe.conditioner_index("visual", "1") == 1


@pytest.mark.parametrize(
    "which, message",
    [
        ("0", r"conditioner 0:label reads samples' 'label', not 'visual'; give a --label condition"),
        ("text", r"--conditioner text is none of this generator's conditioners \(0:label, 1:visual\)"),
        ("7", r"--conditioner 7 is none of"),
    ],
)
def test_a_wrong_choice_is_one_line_naming_the_conditioners(which, message):
    pipe = _pipeline(("label", "label"), ("visual", "visual"))
    with pytest.raises(ConfigError, match=message) as error:
        pipe.conditioner_index("visual", which)
    assert "\n" not in str(error.value)


def test_two_conditioners_of_one_name_are_chosen_by_index():
    pipe = _pipeline(("visual", "visual"), ("visual", "visual"))
    with pytest.raises(ConfigError, match="names several"):
        pipe.conditioner_index("visual", "visual")
    assert pipe.conditioner_index("visual", 1) == 1

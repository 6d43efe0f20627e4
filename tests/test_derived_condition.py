"""A conditioner may read any sample entry or a value derived from the sample (here a material from the
class name), with the class names in its build context; it trains and samples end to end."""

from __future__ import annotations

import json

import pytest
import torch

from derived_condition_plugin import MATERIALS, material_of
from generator_runs import train_args
from vqtouch.core import BuildContext, load_plugins, read_metadata
from vqtouch.plugins.cli.app import main
from vqtouch.plugins.testing import check_plugin


@pytest.fixture
def with_plugin(monkeypatch):
    monkeypatch.setenv("VQTOUCH_PLUGINS", "derived_condition_plugin")


def test_the_derived_condition_follows_the_class_names():
    host = load_plugins(autoload=False, extra=["derived_condition_plugin"])
    names = ("sphere", "cube", "knurled_cylinder")
    conditioner = host.build("conditioner", "material", BuildContext(num_classes=3, class_names=names, cond_dim=8))
    assert conditioner.sample_entries() == ("label",)
    derived = conditioner.condition_of({"label": torch.tensor([0, 1, 2, 1])})
    assert [MATERIALS[i] for i in derived.tolist()] == [material_of(names[i]) for i in (0, 1, 2, 1)]
    # A batch that already holds the material (what `generate --condition` gives) is used as it is.
    assert conditioner.condition_of({"material": torch.tensor([2])}).tolist() == [2]
    check_plugin(
        host,
        "conditioner",
        "material",
        context=BuildContext(num_classes=3, class_names=names, cond_dim=8),
        condition=torch.tensor([0, 1, 2]),
    )


def test_a_derived_condition_trains_and_samples(with_plugin, tmp_path, capsys):
    run = tmp_path / "run"
    assert main(train_args(run, 'generator.conditioners=[{"name": "material"}]')) == 0
    header = read_metadata(next((run / "checkpoints").rglob("conditioner_0.safetensors")))
    class_names = json.loads(header["vqtouch.context"])["class_names"]
    assert len(class_names) > 1  # the dataset's names reached the factory through the build context
    out = tmp_path / "soft"
    assert (
        main(
            [
                "--no-progress",
                "generate",
                "--run",
                str(run),
                "--condition",
                "material=soft",
                "--n",
                "2",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    settings = json.loads((out / "generate.json").read_text())
    assert settings["condition"] == "material" and settings["conditioner"] == "0:material"
    assert len(list(out.glob("sample_*.png"))) == 2
    capsys.readouterr()
    assert (
        main(
            [
                "--no-progress",
                "generate",
                "--run",
                str(run),
                "--condition",
                "material=glass",
                "--out",
                str(tmp_path / "bad"),
            ]
        )
        == 2
    )
    assert "choose one of rigid, soft, textured" in capsys.readouterr().err

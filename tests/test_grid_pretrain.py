"""``generator.train.grid_pretrain``: the condition grid trained on the contact's place alone before the
generator trains.  The stage runs it on the training split plus newly rendered scenes and records it;
what it trains moves and nothing else does; it is a pure function of the seed; a resumed run does not
repeat it; the config refuses what cannot run in one line; and the procedural dataset's new scenes
are new."""

import json
import re
import shutil

import pytest
import torch
from safetensors.torch import load_file

from vqtouch.plugins.cli.app import main
from vqtouch.core import BuildContext, load_plugins, resolve_config
from vqtouch.core.assembly import Assembly
from vqtouch.plugins.generator.grid_pretrain import GridPretrainConfig, grid_conditioners, pretrain_condition_grid

from generator_runs import TINY, train_args  # noqa: E402  (registered by conftest)

HOST = load_plugins()


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny label-to-touch run (its tokenizer serves the touch-to-touch runs below)."""
    out = tmp_path_factory.mktemp("grid") / "run"
    assert main(train_args(out)) == 0
    return out


def _touch_args(out, trained, *extra):
    overrides = [o for o in TINY if not o.startswith("tokenizer.")] + [
        "generator.conditioners.0.width=8",
        "generator.conditioners.0.depth=1",
        "generator.model.contact_weight=1",
        "generator.train.steps=0",
        "generator.num_samples=0",
        *extra,
    ]
    args = ["--no-progress", "train", "generator", "--scene", "touch-to-touch", "--tokenizer", str(trained)]
    for override in overrides:
        args += ["--set", override]
    return [*args, "--out", str(out)]


def _weights(run, module):
    (folder,) = (run / "checkpoints" / "generator").iterdir()
    return load_file(folder / f"{module}.safetensors")


def test_the_stage_pretrains_the_grid_on_the_training_split_and_new_scenes(trained, tmp_path):
    """With 0 generator steps the checkpoint is the pretrained state: the grid embedding, the contact
    head and the conditioner moved from a run without pretraining, every other generator weight did not;
    generation.json records the scenes (the training split plus the new ones) and a falling loss."""
    plain, pretrained = tmp_path / "plain", tmp_path / "pretrained"
    assert main(_touch_args(plain, trained)) == 0
    steps = ["generator.train.grid_pretrain.steps=40", "generator.train.grid_pretrain.new_scenes=8"]
    assert main(_touch_args(pretrained, trained, *steps)) == 0
    result = json.loads((pretrained / "generation.json").read_text())
    note = result["grid_pretrain"]
    assert note["steps"] == 40 and note["conditioners"] == [0] and note["new_scenes"] == 8
    assert note["scenes"] == result["train_samples"] + 8
    assert note["contact_bce_last"] < note["contact_bce_first"]
    assert "grid_pretrain" not in json.loads((plain / "generation.json").read_text())
    before, after = _weights(plain, "generator"), _weights(pretrained, "generator")
    moved = {key for key in before if not torch.equal(before[key], after[key])}
    assert moved == {"network.grid_proj.weight", "network.grid_proj.bias", "contact_head.weight", "contact_head.bias"}
    conditioner_before, conditioner_after = _weights(plain, "conditioner_0"), _weights(pretrained, "conditioner_0")
    assert any(not torch.equal(conditioner_before[k], conditioner_after[k]) for k in conditioner_before)


def test_a_resumed_run_does_not_pretrain_again(trained, tmp_path):
    """The checkpoint a run resumes from holds the pretrained grid: resuming does not pretrain again."""
    run = tmp_path / "resumed"
    steps = ["generator.train.grid_pretrain.steps=5", "generator.train.steps=2", "generator.train.checkpoint_every=1"]
    assert main(_touch_args(run, trained, *steps)) == 0
    assert "grid_pretrain" in json.loads((run / "generation.json").read_text())
    shutil.rmtree(run / "checkpoints" / "generator" / "step-00000002")
    assert main(["--no-progress", "train", "generator", "--resume", str(run)]) == 0
    result = json.loads((run / "generation.json").read_text())
    assert result["step"] == 2 and "grid_pretrain" not in result


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["generator.model.contact_weight=0", "generator.train.grid_pretrain.steps=3"],
         "generator.train.grid_pretrain.steps > 0 trains the contact head, which generator.model.contact_weight > 0"),
        (["generator.train.grid_pretrain.steps=3", "generator.train.grid_pretrain.conditioners=[1]"],
         r"grid_pretrain.conditioners names \[1\], outside generator.conditioners \(0..0\)"),
        (["generator.train.grid_pretrain.new_scenes=3"],
         "grid_pretrain.new_scenes is set but grid_pretrain.steps is 0"),
    ],
)  # fmt: skip
def test_the_config_refuses_a_pretraining_that_cannot_run(overrides, message, trained, tmp_path, capsys):
    capsys.readouterr()
    assert main(_touch_args(tmp_path / "refused", trained, *overrides)) == 2
    error = capsys.readouterr().err
    assert len(error.strip().splitlines()) == 1
    assert re.search(message, error)
    assert not (tmp_path / "refused" / "checkpoints").exists()


CONTEXT = BuildContext(image_size=32, cond_dim=8, codebook_size=16, code_grid=4)


def _pieces():
    torch.manual_seed(0)
    options = {"depth": 1, "width": 16, "heads": 2, "num_steps": 10, "contact_weight": 1.0}
    generator = HOST.build("generator", {"name": "vq_diffusion", **options}, CONTEXT)
    tactile = HOST.build("conditioner", {"name": "tactile", "width": 8, "depth": 1}, CONTEXT)
    label = HOST.build("conditioner", {"name": "label", "num_classes": 3}, CONTEXT)
    return generator, [label, tactile]


def _data(count=12):
    draw = torch.Generator().manual_seed(5)
    images = torch.rand(count, 3, 32, 32, generator=draw)
    # The contact is where the image's red channel is bright: a place the grid can read.
    contact = torch.nn.functional.adaptive_avg_pool2d(images[:, :1], 4)[:, 0] > 0.5
    entries = {"tactile_source": images, "label": torch.randint(3, (count,), generator=draw)}
    return entries, contact


def test_the_grid_conditioners_are_those_whose_condition_has_a_grid():
    generator, conditioners = _pieces()
    entries, _ = _data()
    example = {key: value[:1] for key, value in entries.items()}
    assert grid_conditioners(conditioners, example, None) == [1]
    assert grid_conditioners(conditioners, example, [1]) == [1]
    refusal = r"conditioners names 0, which gives no condition grid \(those that do: \[1\]\)"
    with pytest.raises(ValueError, match=refusal):
        grid_conditioners(conditioners, example, [0])
    with pytest.raises(ValueError, match="no conditioner gives a condition grid"):
        grid_conditioners(conditioners[:1], example, None)


def test_pretraining_lowers_the_contact_loss_and_is_a_function_of_the_seed():
    entries, contact = _data()
    config = GridPretrainConfig(steps=60, learning_rate=3e-3)
    runs = []
    for _ in range(2):
        generator, conditioners = _pieces()
        note = pretrain_condition_grid(generator, conditioners, entries, contact, config, [1], batch_size=4, seed=3)
        runs.append((generator.state_dict(), conditioners[1].state_dict(), conditioners[0].state_dict(), note))
    first, second = runs
    assert first[3]["contact_bce_last"] < 0.8 * first[3]["contact_bce_first"]
    assert all(torch.equal(first[0][k], second[0][k]) for k in first[0])
    assert all(torch.equal(first[1][k], second[1][k]) for k in first[1])
    untouched = _pieces()[1][0].state_dict()
    assert all(torch.equal(first[2][k], untouched[k]) for k in untouched)  # the label conditioner did not train
    generator, conditioners = _pieces()
    other = pretrain_condition_grid(generator, conditioners, entries, contact, config, [1], batch_size=4, seed=4)
    assert not torch.equal(generator.state_dict()["contact_head.weight"], first[0]["contact_head.weight"])
    assert other["steps"] == 60


def test_a_generator_without_a_contact_head_is_refused():
    entries, contact = _data()
    generator = HOST.build("generator", {"name": "vq_diffusion", "depth": 1, "width": 16, "heads": 2}, CONTEXT)
    _, conditioners = _pieces()
    with pytest.raises(ValueError, match="needs a generator with a contact head"):
        pretrain_condition_grid(
            generator, conditioners, entries, contact, GridPretrainConfig(steps=2), [1], batch_size=2, seed=0
        )


def test_new_procedural_scenes_are_new_draws_of_the_same_dataset():
    config = resolve_config("touch-to-touch", overrides=["data.image_size=32", "data.dataset.num_samples=6"], host=HOST)
    dataset = Assembly(config, HOST).component("data.dataset")
    fresh = dataset.new_scenes(4)
    assert len(fresh) == 4 and fresh.class_names == dataset.class_names
    assert fresh.config.seed == dataset.config.seed + 1000 and fresh.config.image_size == dataset.config.image_size
    ours, theirs = dataset.render_batch([0, 1]), fresh.render_batch([0, 1])
    assert set(ours) == set(theirs)  # the paired sensor's image too
    assert not torch.equal(ours["tactile"], theirs["tactile"]) and not set(ours["id"]) & set(theirs["id"])
    with pytest.raises(ValueError, match="draw at least one scene"):
        dataset.new_scenes(0)
    with pytest.raises(ValueError, match="draws this dataset's own scenes again"):
        dataset.new_scenes(2, seed_offset=0)

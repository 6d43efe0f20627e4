"""``vqtouch evaluate reconstruction --out``: reconstruction against training-set size (Table 1), and the
``data.train_samples`` split it varies."""

from __future__ import annotations

import json
import statistics

import pytest
import torch

from generator_runs import TINY
from vqtouch.core import ConfigError, resolve_config
from vqtouch.plugins.cli.app import main
from vqtouch.core.config import DataConfig
from vqtouch.plugins.utils.splits import experiment_split, split_dataset
from vqtouch.plugins.tokenizer import experiment as table1
from vqtouch.plugins.tokenizer.experiment import BACKGROUND, plan_configs, verdict_lines

#: The tokenizer part of the tiny generator runs, plus a tiny MAE.
TOKENIZER = [item for item in TINY if not item.startswith("generator.") and not item.startswith("data.dataset")]


class Numbered(torch.utils.data.Dataset):
    """Samples that are their own index (a dataset with no groups)."""

    def __init__(self, size: int) -> None:
        self.size = size

    def __len__(self) -> int:
        return self.size

    def __getitem__(self, index: int) -> dict:
        return {"index": index}


@pytest.mark.parametrize("seed", [0, 3])
def test_train_samples_are_nested_draws_of_the_training_split_and_leave_the_held_out_split_alone(seed):
    dataset = Numbered(50)
    train, held_out = split_dataset(dataset, 0.2, seed)
    chosen = {}
    for count in (5, 20, 40):
        subset, same_held_out = experiment_split(dataset, DataConfig(val_fraction=0.2, train_samples=count), seed)
        assert same_held_out.indices == held_out.indices
        assert len(subset) == count and set(subset.indices) <= set(train.indices)
        assert subset.indices == sorted(subset.indices)  # dataset order, whatever the draw
        chosen[count] = set(subset.indices)
    assert chosen[5] < chosen[20] < chosen[40]  # more data adds samples, never swaps them
    everything, _ = experiment_split(dataset, DataConfig(val_fraction=0.2), seed)
    assert everything.indices == train.indices
    other_seed, _ = experiment_split(dataset, DataConfig(val_fraction=0.2, train_samples=5), seed + 1)
    assert set(other_seed.indices) != chosen[5]


def test_more_train_samples_than_the_training_split_holds_is_one_line():
    with pytest.raises(
        ConfigError,
        match=r"^data.train_samples=41, but the training split holds 40 samples "
        r"\(50 in the dataset, 10 held out\); lower data.train_samples",
    ):
        experiment_split(Numbered(50), DataConfig(val_fraction=0.2, train_samples=41), 0)


def test_the_models_keep_the_scenes_shared_options_and_the_mae_is_continuous(host):
    config = resolve_config("reconstruction", overrides=["tokenizer.autoencoder.channels=32"], host=host)
    runs = plan_configs(
        config, host, samples=[10, 30], models=["vqgan", "dm_vqgan"], mae_ratios=[0.5], held_out=12, seed=4
    )
    assert [(label, count) for label, count, _ in runs] == [
        ("vqgan", 10),
        ("vqgan", 30),
        ("dm_vqgan", 10),
        ("dm_vqgan", 30),
        ("mae (mask 0.5)", 10),
        ("mae (mask 0.5)", 30),
    ]
    by_label = {label: run for label, _, run in runs}
    assert by_label["vqgan"].tokenizer.autoencoder.name == "vqgan"
    assert by_label["vqgan"].tokenizer.autoencoder.channels == 32  # the scene's option holds for every model
    assert by_label["dm_vqgan"].tokenizer.autoencoder.channels == 32
    assert by_label["vqgan"].tokenizer.quantizer == config.tokenizer.quantizer
    assert by_label["vqgan"].tokenizer.discriminator == config.tokenizer.discriminator
    mae = by_label["mae (mask 0.5)"].tokenizer
    assert (mae.autoencoder.name, mae.autoencoder.mask_ratio, mae.quantizer.name, mae.discriminator) == (
        "mae",
        0.5,
        "identity",
        None,
    )
    for _, count, run in runs:
        assert run.stages == ["tokenizer"] and run.seed == 4 and run.data.train_samples == count
        # Exactly --held-out procedural samples are held out, the same ones for every model and N.
        assert run.data.dataset.num_samples == 42
        dataset = torch.utils.data.TensorDataset(torch.zeros(42))
        assert len(split_dataset(dataset, run.data.val_fraction, run.seed)[1]) == 12


def test_a_size_the_data_cannot_give_is_refused_before_anything_trains(host, tmp_path, monkeypatch):
    from PIL import Image

    root = tmp_path / "frames"
    for index in range(12):
        folder = root / ("a" if index % 2 else "b")
        folder.mkdir(parents=True, exist_ok=True)
        Image.new("RGB", (40, 40), (index * 20, 90, 120)).save(folder / f"{index}.png")
    monkeypatch.setattr(table1, "train_and_score", lambda *args: pytest.fail("trained before refusing"))
    config = resolve_config(
        "reconstruction",
        overrides=[f'data.dataset={{"name": "image_folder", "root": "{root}"}}', "data.val_fraction=0.25"],
        host=host,
    )
    with pytest.raises(
        ConfigError,
        match=r"^--samples 10: the training split of 'image_folder' holds 9 samples "
        r"\(12 in the dataset\); use --samples up to 9",
    ):
        table1.evaluate_reconstruction_experiment(
            config, host, tmp_path / "out", seeds=[0], samples=[4, 10], models=["vqgan"], mae_ratios=[], held_out=None
        )
    with pytest.raises(
        ConfigError,
        match="--held-out sets how many procedural samples are held out; the dataset "
        "'image_folder' holds out data.val_fraction=0.25",
    ):
        plan_configs(config, host, samples=[4], models=["vqgan"], mae_ratios=[], held_out=5, seed=0)


def test_verdicts_name_the_best_model_and_count_gaps_beyond_the_spread():
    summary = [
        {"model": "vqgan", "samples": 100, "contact_psnr": 20.0, "contact_psnr_std": 0.2},
        {"model": "dm_vqgan", "samples": 100, "contact_psnr": 21.0, "contact_psnr_std": 0.2},
        {"model": "mae (mask 0.5)", "samples": 100, "contact_psnr": 20.9, "contact_psnr_std": 0.0},
        {"model": BACKGROUND, "samples": 100, "contact_psnr": 25.0, "contact_psnr_std": 0.1},
    ]
    assert verdict_lines(summary) == [
        "- N = 100: `dm_vqgan` is level with `mae (mask 0.5)` (gap +0.1 within the spread 0.2) on contact_psnr.",
        "- N = 100: `dm_vqgan` beats `vqgan` by 1 on contact_psnr.",
        "- N = 100: `dm_vqgan` is behind `no-contact background` by 4 on contact_psnr.",
    ]


def experiment_args(out, *extra):
    args = [
        "--no-progress",
        "evaluate",
        "reconstruction",
        "--out",
        str(out),
        "--samples",
        "4",
        "8",
        "--seeds",
        "0",
        "1",
        "--held-out",
        "6",
        "--models",
        "vqgan",
        "--mae-ratios",
        "0.5",
        "--no-distribution",
        *extra,
    ]
    for override in [*TOKENIZER, "tokenizer.train.checkpoint_every=2"]:
        args += ["--set", override]
    return args


@pytest.fixture(scope="module")
def experiment(tmp_path_factory):
    out = tmp_path_factory.mktemp("reconstruction") / "exp"
    assert main(experiment_args(out)) == 0
    return out, json.loads((out / "reconstruction.json").read_text())


def test_every_seed_size_and_model_trains_on_exactly_n_samples_and_is_scored_on_one_held_out_set(experiment):
    out, result = experiment
    for name in ("reconstruction.md", "reconstruction.png", "reconstruction_samples.png"):
        assert (out / name).stat().st_size > 0
    models = {("vqgan", "vqgan"), ("mae (mask 0.5)", "mae-mask0.5")}
    trained = [row for row in result["rows"] if row["model"] != BACKGROUND]
    assert sorted((row["model"], row["samples"], row["seed"]) for row in trained) == sorted(
        (label, count, seed) for label, _ in models for count in (4, 8) for seed in (0, 1)
    )
    for label, folder in models:
        for count in (4, 8):
            for seed in (0, 1):
                # What the tokenizer stage itself recorded of its training and held-out sets.
                evaluation = json.loads((out / "runs" / f"{folder}-{count}" / f"seed{seed}" / "eval.json").read_text())
                assert (evaluation["train_samples"], evaluation["val_samples"]) == (count, 6)
    # One no-contact row per seed and N, scored on the same held-out images as the models.
    background = [row for row in result["rows"] if row["model"] == BACKGROUND]
    assert sorted((row["samples"], row["seed"]) for row in background) == [(4, 0), (4, 1), (8, 0), (8, 1)]
    for row in background:
        evaluation = json.loads((out / "runs" / "vqgan-4" / f"seed{row['seed']}" / "eval.json").read_text())
        assert row["psnr"] == evaluation["background_psnr"]
        assert row["contact_psnr"] == evaluation["background_contact_psnr"]
    text = (out / "reconstruction.md").read_text()
    assert "| no-contact background | 4 |" in text and "Verdicts (contact region only" in text


def test_the_summary_is_the_mean_and_spread_of_the_seeds(experiment):
    _, result = experiment
    for entry in result["summary"]:
        values = [
            row["psnr"]
            for row in result["rows"]
            if row["model"] == entry["model"] and row["samples"] == entry["samples"]
        ]
        assert entry["psnr"] == pytest.approx(sum(values) / len(values), abs=1e-6)
        assert entry["psnr_std"] == pytest.approx(statistics.pstdev(values), abs=1e-6)


def test_a_second_call_refuses_to_overwrite_and_run_only_flags_are_refused(experiment, tmp_path, capsys):
    out, _ = experiment
    assert main(experiment_args(out)) == 2
    assert "already holds a reconstruction experiment; pass --overwrite" in capsys.readouterr().err
    assert main(experiment_args(tmp_path / "x", "--split", "all")) == 2
    assert "--step, --split, --metrics and --dataset score one run (--run)" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
    # A bad option of one model is refused before the experiment makes its folder.
    assert main(experiment_args(tmp_path / "y", "--mae-ratios", "0.5", "1.5")) == 2
    assert "argument --mae-ratios: 1.5: must be a finite number in [0, 1)" in capsys.readouterr().err
    assert not (tmp_path / "y").exists()


def test_a_rerun_reuses_finished_runs_and_retrains_a_changed_one(experiment, monkeypatch, capsys):
    out, result = experiment
    monkeypatch.setattr(table1, "run_stage", lambda *args, **kwargs: pytest.fail("a finished run was trained again"))
    assert main(experiment_args(out, "--overwrite")) == 0
    assert capsys.readouterr().out.count("[reused]") == 8
    again = json.loads((out / "reconstruction.json").read_text())
    assert again["rows"] == result["rows"]
    # One changed option: the run is trained again (here, the stand-in refuses to).
    with pytest.raises(pytest.fail.Exception, match="a finished run was trained again"):
        main(experiment_args(out, "--overwrite", "--set", "tokenizer.train.learning_rate=0.001"))

"""Few-shot generation for an unseen sensor (`vqtouch fewshot`): the sensor tag, the
mixed fine-tuning set, the command from a sensor's images to a generator run of that sensor, and its
bad inputs."""

import json
import shutil

import pytest
import torch

import generator_runs
from cli_checks import one_error_line, snapshot
from vqtouch.core import ConfigError, load_plugins
from vqtouch.plugins.cli.app import main
from vqtouch.plugins.utils.images import save_png
from vqtouch.plugins.runtime.outputs import MARKER_NAME
from vqtouch.plugins.experiments.fewshot_scoring import RECONSTRUCTED
from vqtouch.plugins.generator.sensor_finetune import FAMILY_SENSOR, NEW_SENSOR, mixed_codes
from vqtouch.plugins.generator.training import (
    CodesDataset,
    GeneratorTask,
    SensorTaggedConditioner,
    absent_key,
)

HOST = load_plugins()
HOST_CONTEXT = {"host": HOST}


def _variant(name, seed, **variant):
    return json.dumps({"name": name, "variant": {"seed": seed, **variant}})


TARGET = _variant("gelsight", 5, colour_gain=[0.8, 1.0, 1.1])


def _label_conditioner(cond_dim=8, classes=3):
    from vqtouch.core import BuildContext

    return HOST.build("conditioner", {"name": "label", "num_classes": classes}, BuildContext(cond_dim=cond_dim))


def _tag(cond_dim=8):
    from vqtouch.core import BuildContext

    return HOST.build("conditioner", {"name": "sensor", "num_sensors": 2}, BuildContext(cond_dim=cond_dim))


def test_a_new_tag_leaves_every_condition_as_it_was_and_a_trained_one_offsets_condition_and_null_alike():
    torch.manual_seed(0)
    label, tag = _label_conditioner(), _tag()
    labels = torch.tensor([0, 2, 1])
    tagged = SensorTaggedConditioner(label, tag, NEW_SENSOR)
    plain = label(labels)
    # Zero offsets: the fine-tuning starts from exactly the family generator's conditions.
    assert torch.equal(tagged(labels).tokens_BND, plain.tokens_BND)
    assert torch.equal(tagged.null(3).tokens_BND, label.null(3).tokens_BND)
    with torch.no_grad():
        tag.offsets_SD[NEW_SENSOR] = torch.arange(8.0)
    shifted = tagged(labels)
    assert torch.allclose(shifted.tokens_BND - plain.tokens_BND, torch.arange(8.0).expand(3, 1, 8))
    assert torch.allclose(tagged.null(3).tokens_BND - label.null(3).tokens_BND, torch.arange(8.0).expand(3, 1, 8))
    # The family's sensor keeps its own (zero) offset; the wrapper reads and parses as the label does.
    assert torch.equal(SensorTaggedConditioner(label, tag, FAMILY_SENSOR)(labels).tokens_BND, plain.tokens_BND)
    assert tagged.sample_key == "label" and tagged.parse_condition("1", image_size=32) == 1
    with pytest.raises(ValueError, match="outside the tag's 2 sensors"):
        SensorTaggedConditioner(label, tag, 2)


def test_rows_that_lack_a_condition_train_with_the_null_condition_and_carry_their_sensors_offset():
    torch.manual_seed(0)
    label, tag = _label_conditioner(), _tag()
    with torch.no_grad():
        tag.offsets_SD[1] = 1.0
    task = GeneratorTask(torch.nn.Linear(1, 1), [label], 0.0, seed=0, sensor_tag=tag)
    batch = {
        "codes": torch.zeros(3, 2, 2, dtype=torch.long),
        "label": torch.tensor([2, 0, 1]),
        absent_key("label"): torch.tensor([False, True, False]),
        "sensor_index": torch.tensor([0, 1, 1]),
    }
    tokens = task.condition_tokens(0, batch, None)
    assert tokens.is_null_B.tolist() == [False, True, False]
    expected = torch.stack(
        [
            label(torch.tensor([2])).tokens_BND[0],
            label.null(1).tokens_BND[0] + 1,
            label(torch.tensor([1])).tokens_BND[0] + 1,
        ]
    )
    assert torch.allclose(tokens.tokens_BND, expected)
    assert "sensor_tag" in task.modules


def test_the_mix_holds_the_family_rows_then_the_shots_with_their_conditions_absent():
    family = CodesDataset(
        torch.arange(5 * 4).view(5, 2, 2),
        {"label": torch.tensor([0, 1, 2, 0, 1]), "text": ["a", "b", "c", "d", "e"]},
        class_names=["x", "y", "z"],
    )
    shots = torch.full((2, 2, 2), 7)
    mix = mixed_codes(family, shots, ["label", "text"], "sensor_index")
    assert len(mix) == 7 and mix.class_names == ["x", "y", "z"]
    assert torch.equal(mix.codes_NHW[5:], shots) and torch.equal(mix.codes_NHW[:5], family.codes_NHW)
    assert mix.entries["sensor_index"].tolist() == [0] * 5 + [1] * 2
    for key in ("label", "text"):
        assert mix.entries[absent_key(key)].tolist() == [False] * 5 + [True] * 2
    assert mix.entries["label"][:5].tolist() == [0, 1, 2, 0, 1] and mix.entries["text"][:5] == ["a", "b", "c", "d", "e"]


@pytest.fixture(scope="module")
def family(tmp_path_factory):
    """A tiny label-to-touch family run and families clustered with its tokenizer."""
    root = tmp_path_factory.mktemp("family")
    assert main(generator_runs.train_args(root / "run")) == 0
    assert (
        main(
            [
                "--no-progress",
                "cluster",
                "--run",
                str(root / "run"),
                "--image-size",
                "32",
                "--images",
                "8",
                "--out",
                str(root / "families"),
                "--families",
                "2",
                "--sensors",
                "gelsight",
                _variant("gelsight", 1, colour_gain=[1.05, 0.95, 0.95]),
                "digit",
                _variant("digit", 2, noise_std=0.02),
            ]
        )
        == 0
    )
    return root


def _fewshot(family, out, images=TARGET, *extra):
    return main(
        [
            "--no-progress",
            "fewshot",
            "--run",
            str(family / "run"),
            "--images",
            images,
            "--out",
            str(out),
            "--families",
            str(family / "families"),
            "--shots",
            "4",
            "--tokenizer-steps",
            "2",
            "--generator-steps",
            "3",
            "--samples",
            "4",
            "--eval-images",
            "4",
            "--feature-size",
            "32",
            "--threshold",
            "1",
            *extra,
        ]
    )


def test_fewshot_goes_from_a_sensors_images_to_a_generator_run_that_draws_that_sensor(family, tmp_path, capsys):
    from vqtouch.plugins.generator import load_pipeline

    out = tmp_path / "fewshot"
    assert _fewshot(family, out) == 0
    printed = capsys.readouterr().out
    steps = [line for line in printed.splitlines() if line[:2] in {"1/", "2/", "3/", "4/", "5/"}]
    assert [line[:3] for line in steps] == ["1/5", "2/5", "3/5", "4/5", "5/5"]
    result = json.loads((out / "fewshot.json").read_text())
    assert result["adapt"]["assignment"]["family"] == 0  # a GelSight variant joins the GelSight family
    tune = result["fine_tune"]
    assert tune["shots"] == 4 and tune["family_samples"] == 4  # 1 per shot: vqtouch adapt's default ratio
    arms = {(row["conditioner"], row["arm"]) for row in result["scores"]}
    scored = ("few-shot", "zero-shot", "shots (copied)", "no-contact background")
    assert arms == {("0:label", arm) for arm in (*scored, RECONSTRUCTED)}
    assert all(row["fd_effnetlite0"] >= 0 for row in result["scores"] if row["arm"] in scored)
    # The label samples are classified by one trained on the new sensor's images of the 18 training scenes.
    assert result["classifier"]["train_images"] == 18
    accuracy = {row["arm"]: row.get("classifier_accuracy") for row in result["scores"]}
    assert accuracy["shots (copied)"] is None and accuracy["no-contact background"] is None
    assert all(0 <= accuracy[arm] <= 1 for arm in ("few-shot", "zero-shot", RECONSTRUCTED))
    # A registered variant renders the family's held-out contacts: paired contact scores, but for the copies.
    assert result["paired_truth"] is True
    paired = {row["arm"]: row.get("contact_psnr") for row in result["scores"] if row["arm"] != RECONSTRUCTED}
    assert paired["shots (copied)"] is None and all(0 < paired[arm] < 100 for arm in paired if arm != "shots (copied)")
    assert (out / "samples_0_label.png").is_file() and "| few-shot |" in (out / "fewshot.md").read_text()
    # The records name final paths, never the staging folder the run was written in.
    assert tune["tokenizer"] == str((out / "tokenizer").resolve())
    recorded = json.loads((out / "generator" / "fewshot_finetune.json").read_text())["tokenizer"]
    assert recorded == "../tokenizer" and (out / "generator" / recorded / "autoencoder.safetensors").is_file()
    assert ".partial" not in (out / "fewshot.json").read_text() + (out / "generator" / "config.json").read_text()
    # The output is a generator run drawing the new sensor; moved whole, it still finds its tokenizer.
    moved = tmp_path / "elsewhere"
    shutil.move(str(out), str(moved))
    pipe = load_pipeline(moved / "generator", host=HOST)
    assert pipe.sensor_tag is not None and pipe.config.generator.sample_sensor == NEW_SENSOR
    assert pipe.sensor_tag.sensor_names == ["gelsight", "gelsight/v5"]
    images = pipe(label=1, n=2, steps=2, seed=0)
    assert images.shape == (2, 3, 32, 32) and torch.isfinite(images).all()
    # Its tag was trained: the new sensor's offset moved from zero, the family's stays at its start.
    assert pipe.sensor_tag.offsets_SD[NEW_SENSOR].abs().sum() > 0
    assert (
        main(
            [
                "--no-progress",
                "generate",
                "--run",
                str(moved / "generator"),
                "--label",
                "0",
                "--out",
                str(tmp_path / "g"),
            ]
        )
        == 0
    )


@pytest.mark.parametrize("stop", ["fine-tuning", "scoring"])
def test_an_interrupted_fewshot_says_that_nothing_is_kept_and_keeps_what_out_held(
    family, tmp_path, capsys, monkeypatch, stop
):
    import vqtouch.plugins.experiments.fewshot_generation as fewshot
    from vqtouch.plugins.training.trainer import TrainingInterrupted

    def interrupted(*args, **kwargs):
        if stop == "fine-tuning":  # what the trainer raises after Ctrl-C, once its checkpoint is written
            raise TrainingInterrupted("SIGINT", 1, tmp_path / "checkpoint")
        raise KeyboardInterrupt

    target = "fine_tune_for_sensor" if stop == "fine-tuning" else "sample_and_score"
    if stop == "fine-tuning":
        import vqtouch.plugins.generator as generator

        monkeypatch.setattr(generator, target, interrupted)
    else:
        monkeypatch.setattr(fewshot, target, interrupted)
    out = tmp_path / "fewshot"
    out.mkdir()
    (out / MARKER_NAME).write_text('{"command": "fewshot"}\n')
    (out / "fewshot.json").write_text("an earlier result\n")
    assert _fewshot(family, out, TARGET, "--overwrite") == 130
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.startswith("vqtouch: fewshot stopped by ") and "nothing of this run is kept" in last
    assert "run the command again" in last
    assert (out / "fewshot.json").read_text() == "an earlier result\n"
    assert sorted(path.name for path in tmp_path.iterdir()) == ["fewshot"]  # no staging folder left


def test_only_a_tokenizer_adapted_from_the_familys_own_stands_in_for_adapting(family, tmp_path):
    from vqtouch.plugins.experiments.fewshot_generation import _family_tokenizer, adapted_summary, fewshot_generation

    out = tmp_path / "first"
    assert _fewshot(family, out, TARGET, "--no-score") == 0
    _, folder = _family_tokenizer(str(family / "run"), HOST)
    assert adapted_summary(out / "tokenizer", folder, "decoder")["part"] == "decoder"
    assert adapted_summary(out / "tokenizer", folder, "all") is None  # adapted another way
    elsewhere = tmp_path / "elsewhere"
    shutil.copytree(out / "tokenizer", elsewhere)
    made = json.loads((elsewhere / "adapt.json").read_text())
    (elsewhere / "adapt.json").write_text(json.dumps(made | {"adapted_from": str(tmp_path)}))
    assert adapted_summary(elsewhere, folder) is None
    with pytest.raises(ConfigError, match="was not adapted from"):
        fewshot_generation(str(family / "run"), TARGET, tmp_path / "second", HOST, adapted=elsewhere)
    assert not (tmp_path / "second").exists()


def test_fewshot_rebases_by_default_and_not_with_no_rebase(family, tmp_path):
    from vqtouch.plugins.experiments.fewshot_generation import _family_tokenizer, adapted_summary
    from vqtouch.plugins.tokenizer import REBASE_FILE, load_tokenizer

    assert _fewshot(family, tmp_path / "rebased", TARGET, "--no-score") == 0
    assert _fewshot(family, tmp_path / "plain", TARGET, "--no-score", "--no-rebase") == 0
    rebased, _ = load_tokenizer(tmp_path / "rebased" / "tokenizer", HOST)
    plain, _ = load_tokenizer(tmp_path / "plain" / "tokenizer", HOST)
    assert plain.rebase_3HW is None and not (tmp_path / "plain" / "tokenizer" / REBASE_FILE).exists()
    assert rebased.rebase_3HW is not None and rebased.rebase_3HW.abs().max() > 0
    assert json.loads((tmp_path / "rebased" / "tokenizer" / "adapt.json").read_text())["rebase"] is True
    # The generator run records the rebased folder's digest, so it is refused with the plain tokenizer's.
    _, folder = _family_tokenizer(str(family / "run"), HOST)
    assert adapted_summary(tmp_path / "rebased" / "tokenizer", folder, rebase=False) is None
    assert adapted_summary(tmp_path / "plain" / "tokenizer", folder, rebase=False) is not None


def test_a_folder_of_images_in_class_subfolders_is_a_target(family, tmp_path):
    from vqtouch.plugins.adaptation.families import sensor_images

    images = sensor_images(TARGET, HOST, count=8, image_size=32, seed=3).images
    for index, image in enumerate(images):
        save_png(image, tmp_path / "frames" / f"class{index % 2}" / f"{index}.png")
    out = tmp_path / "out"
    assert _fewshot(family, out, str(tmp_path / "frames"), "--ratio", "0", "--no-score", "--family", "0") == 0
    result = json.loads((out / "fewshot.json").read_text())
    assert result["fine_tune"]["family_samples"] == 0 and result["fine_tune"]["shots"] == 4
    assert result["scores"] == [] and "median" in result["background"] and "paired_truth" not in result


def test_fewshot_bad_inputs_get_one_line_errors_and_write_nothing(family, tmp_path, capsys):
    out = tmp_path / "out"
    (tmp_path / "kept").mkdir()
    (tmp_path / "kept" / "mine.txt").write_text("mine")
    cases = [
        (["--out", str(tmp_path / "kept")], "already holds files"),
        (["--run", str(tmp_path / "kept")], "not a run directory"),
        (["--images", str(tmp_path / "missing")], "missing"),
        (["--shots", "0"], "--shots"),
        (["--ratio", "-1"], "--ratio"),
        ([], "matches no sensor family"),  # the tiny families' own threshold refuses this variant
    ]
    for extra, expected in cases:
        args = [
            "--no-progress",
            "fewshot",
            "--run",
            str(family / "run"),
            "--images",
            TARGET,
            "--out",
            str(out),
            "--families",
            str(family / "families"),
            "--tokenizer-steps",
            "1",
            "--generator-steps",
            "1",
        ]
        # a flag given twice: argparse keeps the last
        code = main([*args, *extra])
        assert code != 0, extra
        assert expected in one_error_line(capsys), extra
        assert not out.exists()
    assert (tmp_path / "kept" / "mine.txt").read_text() == "mine"


def test_a_sensor_tag_needs_the_sensor_conditioner_and_a_sensor_it_has():
    from vqtouch.plugins.generator.stage import GeneratorSection

    with pytest.raises(ValueError, match="sample_sensor is set but generator.sensor_tag is not"):
        GeneratorSection.model_validate({"sample_sensor": 1})
    with pytest.raises(ValueError, match="sensor_tag has 2 sensors"):
        GeneratorSection.model_validate({"sensor_tag": {"name": "sensor"}, "sample_sensor": 2}, context=HOST_CONTEXT)
    with pytest.raises(ValueError, match="must be 'sensor'"):
        GeneratorSection.model_validate({"sensor_tag": {"name": "label"}}, context=HOST_CONTEXT)
    tagged = {"sensor_tag": {"name": "sensor"}, "sample_sensor": 1}
    assert GeneratorSection.model_validate(tagged, context=HOST_CONTEXT).sample_sensor == 1


def test_tagged_runs_are_refused_by_the_generator_stage_and_by_bundle_export(family, tmp_path, capsys):
    out = tmp_path / "fewshot"
    assert _fewshot(family, out, TARGET, "--no-score") == 0
    capsys.readouterr()
    assert (
        main(
            [
                "--no-progress",
                "pretrained",
                "export",
                "--run",
                str(out / "generator"),
                "--name",
                "x",
                "--root",
                str(tmp_path / "bundles"),
            ]
        )
        != 0
    )
    assert "cannot be bundled" in one_error_line(capsys)
    assert not (tmp_path / "bundles" / "x").exists()
    assert (
        main(
            [
                "--no-progress",
                "train",
                "generator",
                "--config",
                str(out / "generator" / "config.json"),
                "--out",
                str(tmp_path / "again"),
            ]
        )
        != 0
    )
    assert "vqtouch fewshot" in capsys.readouterr().err


def test_the_seeds_table_names_each_arm_once_per_conditioner_and_resumes_without_training_again(
    family, tmp_path, capsys
):
    out = tmp_path / "table"
    args = [
        "--no-progress", "evaluate", "fewshot-generation", "--run", str(family / "run"), "--images", TARGET,
        "--out", str(out), "--families", str(family / "families"), "--threshold", "1", "--shots", "4",
        "--tokenizer-steps", "1", "--generator-steps", "1", "--samples", "3", "--eval-images", "3",
        "--feature-size", "32", "--seeds", "0", "--ratios", "2", "0",
    ]  # fmt: skip
    assert main(args) == 0
    first = json.loads((out / "fewshot_generation.json").read_text())
    arms = [(row["conditioner"], row["arm"]) for row in first["summary"]]
    expected = [
        "few-shot 1:2",
        "zero-shot",
        "shots (copied)",
        "no-contact background",
        "new sensor, reconstructed by the 1:2 tokenizer (ceiling)",
        "shots alone",
        "new sensor, reconstructed by the shots-alone tokenizer (ceiling)",
    ]
    assert arms == [("0:label", arm) for arm in expected]
    alone = json.loads((out / "seed0" / "ratio0" / "fewshot.json").read_text())
    assert alone["fine_tune"]["family_samples"] == 0
    assert first["summary"][-2]["fd_effnetlite0"] == alone["scores"][0]["fd_effnetlite0"]
    capsys.readouterr()
    assert main(args) == 2  # a finished table is replaced only with --overwrite
    assert "already holds a fewshot-generation experiment; pass --overwrite" in capsys.readouterr().err
    stamp = (out / "seed0" / "ratio2" / "fewshot.json").stat().st_mtime_ns
    (out / "fewshot_generation.json").unlink()  # as if stopped after its arms, before the table
    finished = snapshot(out)
    other_shots = [*args[:-7], "--shots", "5", *args[-7:]]  # argparse keeps the last --shots
    assert main(other_shots) == 2  # once: trained again and replaced seed0/ratio2 without a word
    assert one_error_line(capsys) == (
        f"{out / 'seed0' / 'ratio2'} holds a finished arm with other settings: shots 4 (now 5); pass --overwrite "
        "to run every arm again, or choose another --out"
    )
    assert snapshot(out) == finished
    assert main(args) == 0
    assert "seed 0, ratio 2: read" in capsys.readouterr().out
    assert (out / "seed0" / "ratio2" / "fewshot.json").stat().st_mtime_ns == stamp
    assert json.loads((out / "fewshot_generation.json").read_text())["summary"] == first["summary"]
    # A run written before the paired scores existed is scored again: the same draws, the same fd.
    done = out / "seed0" / "ratio2" / "fewshot.json"
    older = json.loads(done.read_text())
    del older["paired_truth"], older["classifier"]
    older["scores"] = [
        {key: row[key] for key in ("conditioner", "arm", "fd_effnetlite0")}
        for row in older["scores"]
        if row["arm"] != RECONSTRUCTED
    ]
    done.write_text(json.dumps(older))
    (out / "fewshot_generation.json").unlink()
    capsys.readouterr()
    assert main(args) == 0
    assert "drawing its samples again" in capsys.readouterr().out
    again = json.loads(done.read_text())
    assert again["paired_truth"] is True and again["classifier"]["train_images"] == 18
    assert [row["fd_effnetlite0"] for row in again["scores"] if row["arm"] != RECONSTRUCTED] == [
        row["fd_effnetlite0"] for row in older["scores"]
    ]
    assert json.loads((out / "fewshot_generation.json").read_text())["summary"] == first["summary"]


def test_paired_truth_is_the_new_sensor_drawing_the_family_datas_own_contacts(family, tmp_path):
    from vqtouch.core import Assembly
    from vqtouch.plugins.adaptation import sensor_background
    from vqtouch.plugins.evaluation.contact import contact_centroids, dataset_background
    from vqtouch.plugins.experiments.fewshot_scoring import paired_truth
    from vqtouch.plugins.generator import load_pipeline

    config = load_pipeline(family / "run", host=HOST).config
    dataset = Assembly(config, HOST).component("data.dataset")
    indices = [0, 3, 5, 7]
    truth = paired_truth(config, TARGET, indices, HOST)
    own = torch.stack([dataset[i]["tactile"] for i in indices])
    assert truth.shape == own.shape and not torch.allclose(truth, own)  # another sensor's drawing ...
    own_background, _ = dataset_background(dataset, (32, 32))
    new_background, _ = sensor_background(TARGET, HOST, 32)
    # ... of the same contacts: each image's contact sits where the family image's does.
    shift = contact_centroids(truth, new_background) - contact_centroids(own, own_background)
    assert shift.norm(dim=1).max() < 3.0, shift
    assert paired_truth(config, str(tmp_path), [0], HOST) is None  # a folder pairs with nothing


def test_the_samples_classifier_names_a_class_by_what_the_sensor_draws_for_it():
    """Closed form: two classes the sensor draws as a dark and a bright image, an identity tokenizer.
    Samples drawn right score 1 (as the ceiling does), swapped 0, half swapped 0.5."""
    from vqtouch.plugins.experiments.fewshot_scoring import _classifier_scores

    class Identity:
        device = torch.device("cpu")

        def reconstruct(self, images):
            return images, None

    torch.manual_seed(0)
    dark, bright = torch.full((3, 32, 32), 0.2), torch.full((3, 32, 32), 0.8)

    def draw(labels):
        return torch.stack([(bright if label else dark) + 0.02 * torch.rand(3, 32, 32) for label in labels])

    train_labels = [0, 1] * 8
    labels = [0, 1, 1, 0]
    generated = {
        "0:label": {"right": draw(labels), "swapped": draw([1 - label for label in labels]), "half": draw([0, 0, 1, 1])}
    }
    metric = HOST.build("metric", {"name": "fd_effnetlite0", "image_size": 32})
    accuracy = _classifier_scores(
        generated, draw(labels), labels, (draw(train_labels), train_labels), Identity(), metric, 0
    )
    assert accuracy == {
        ("0:label", "right"): 1.0,
        ("0:label", "swapped"): 0.0,
        ("0:label", "half"): 0.5,
        ("0:label", RECONSTRUCTED): 1.0,
    }

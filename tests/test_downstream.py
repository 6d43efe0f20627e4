"""`vqtouch evaluate downstream` at toy size: the arms and files, the scores
against closed forms, the summary against an independent mean, the real images each arm trained
on against an independent recomputation of the run's split (no held-out image is ever trained
on), the same run on a folder in the image_folder layout, and the one-line refusals."""

import json
import shutil
import statistics
from collections import Counter

import pytest
import torch

import generator_runs
from vqtouch.core import Assembly, ConfigError
from vqtouch.plugins.runtime.run_dir import RunDir
from vqtouch.plugins.cli.app import main
from vqtouch.plugins.utils.splits import split_dataset
from vqtouch.plugins.utils.images import save_png
from vqtouch.plugins.experiments.downstream import label_conditioner_index, train_and_test
from vqtouch.plugins.experiments.downstream_arms import (
    ARMS,
    CEILING,
    FEW,
    FEW_AND_GENERATED,
    FEW_AND_RECONSTRUCTED,
    GENERATED,
    RECONSTRUCTED,
    LabelledFeatures,
    classification_accuracy_score,
    draw_others,
    draw_shots,
    mixed_arm,
    recognition_scores,
)
from vqtouch.plugins.evaluation.distribution import RealImageClassifier

CLASSES = ["sphere", "edge", "ridges"]
#: Small enough to run in seconds: 32-px features, 2 seeds, 2 shots, 2 generated images per class.
FAST = ["--seeds", "0", "1", "--shots", "2", "--generated-per-class", "2", "--feature-size", "32"]


@pytest.fixture(scope="module")
def label_run(tmp_path_factory):
    """A tiny label-to-touch run over 3 classes: 27 training and 9 held-out samples."""
    out = tmp_path_factory.mktemp("downstream") / "run"
    assert (
        main(
            generator_runs.train_args(
                out,
                f"data.dataset.classes={json.dumps(CLASSES)}",
                "data.dataset.num_samples=36",
                "generator.num_samples=0",
            )
        )
        == 0
    )
    return out


@pytest.fixture(scope="module")
def evaluated(label_run, tmp_path_factory):
    out = tmp_path_factory.mktemp("downstream_out")
    assert main(["--no-progress", "evaluate", "downstream", "--run", str(label_run), "--out", str(out), *FAST]) == 0
    return out, json.loads((out / "downstream.json").read_text())


def _run_dataset(run, host):
    """The run's dataset, built from its saved config, and the config."""
    config = RunDir.open(run).load_config(host)
    return Assembly(config, host).component("data.dataset"), config


def test_every_arm_and_file_is_written_with_scores_in_range(evaluated):
    out, result = evaluated
    assert [(row["arm"], row["seed"]) for row in result["rows"]] == [(arm, seed) for seed in (0, 1) for arm in ARMS]
    for row in result["rows"]:
        assert all(0 <= row[score] <= 1 for score in ("top1", "precision", "recall", "f1")), row
    by_arm = {row["arm"]: row for row in result["rows"] if row["seed"] == 0}
    assert by_arm[GENERATED]["train_images"] == 3 * 2 and by_arm[FEW]["train_images"] == 3 * 2
    assert by_arm[FEW_AND_GENERATED]["train_images"] == 3 * 2 + 3 * 2
    assert result["chance"] == pytest.approx(1 / 3, abs=1e-4)
    counts = result["test_class_counts"]
    assert sum(counts.values()) == result["test_images"] == 9
    assert result["majority"] == pytest.approx(max(counts.values()) / 9, abs=1e-4)
    # A classifier whose training images are all one image names one class: at most the majority rate.
    assert all(row["top1"] <= result["majority"] for row in result["rows"] if row["arm"] == "no-contact background")
    matrix = torch.tensor(result["confusion"]["matrices"][CEILING])
    assert int(matrix.sum()) == 9 and float(matrix.diag().sum() / 9) == pytest.approx(by_arm[CEILING]["top1"], abs=1e-4)
    markdown = (out / "downstream.md").read_text()
    assert "| all real (ceiling) | all | 0 | 27 |" in markdown and "Chance (1 / 3 classes): 0.3333" in markdown
    for name in ("downstream.png", "downstream_confusion.png", "downstream_generated.png"):
        assert (out / name).stat().st_size > 1000, name
    assert result["provenance"]["wall_seconds"] > 0


def test_the_summary_is_the_mean_and_spread_of_the_seeds(evaluated):
    _, result = evaluated
    for arm in ARMS:
        rows = [row for row in result["rows"] if row["arm"] == arm]
        summary = next(row for row in result["summary"] if row["arm"] == arm)
        assert summary["seeds"] == 2
        for score in ("top1", "precision", "recall", "f1"):
            assert summary[score] == pytest.approx(statistics.fmean(row[score] for row in rows), abs=1e-5)
            assert summary[f"{score}_std"] == pytest.approx(statistics.pstdev(row[score] for row in rows), abs=1e-5)


def test_the_cas_ratio_and_the_mixed_gain_are_paired_per_seed(evaluated):
    _, result = evaluated
    top1 = {(row["arm"], row["seed"]): row["top1"] for row in result["rows"]}
    ratios = [top1[(GENERATED, seed)] / top1[(FEW, seed)] for seed in (0, 1)]
    gains = [top1[(FEW_AND_GENERATED, seed)] - top1[(FEW, seed)] for seed in (0, 1)]
    assert result["cas_ratio"] == pytest.approx(
        {"mean": statistics.fmean(ratios), "std": statistics.pstdev(ratios)}, abs=1e-4
    )
    assert result["generated_adds"] == pytest.approx(
        {"mean": statistics.fmean(gains), "std": statistics.pstdev(gains)}, abs=1e-4
    )
    markdown = (evaluated[0] / "downstream.md").read_text()
    assert "CAS ratio (`generated only` top-1 over `real few` top-1 at the same 2 images per class" in markdown


def test_the_cas_ratio_needs_equal_counts_and_a_real_score():
    rows = [
        {"arm": GENERATED, "seed": 0, "top1": 0.3},
        {"arm": FEW, "seed": 0, "top1": 0.6},
        {"arm": GENERATED, "seed": 1, "top1": 0.2},
        {"arm": FEW, "seed": 1, "top1": 0.0},  # no real score: that seed has no ratio
    ]
    assert classification_accuracy_score(rows, shots=5, generated_per_class=10) is None
    assert classification_accuracy_score(rows, shots=10, generated_per_class=10) == {"mean": 0.5, "std": 0.0}


def test_no_arm_trains_on_a_held_out_image(evaluated, label_run, host):
    _, result = evaluated
    dataset, config = _run_dataset(label_run, host)
    train, held_out = split_dataset(dataset, config.data.val_fraction, config.seed)
    assert sorted(result["test_indices"]) == sorted(held_out.indices) and len(held_out.indices) == 9
    for row in result["rows"]:
        assert not set(row["real_indices"]) & set(held_out.indices), row["arm"]
        assert set(row["real_indices"]) <= set(train.indices), row["arm"]
    ceilings = [row for row in result["rows"] if row["arm"] == CEILING]
    assert all(sorted(row["real_indices"]) == sorted(train.indices) for row in ceilings)
    few = {row["seed"]: row["real_indices"] for row in result["rows"] if row["arm"] == FEW}
    for indices in few.values():  # two distinct images of each class, read back from the dataset
        assert len(set(indices)) == 6 and Counter(dataset[i]["label"] for i in indices) == {0: 2, 1: 2, 2: 2}
    assert set(few[0]) != set(few[1])  # the seed draws the shots
    assert [row["real_indices"] for row in result["rows"] if row["arm"] == FEW_AND_GENERATED] == [few[0], few[1]]


def test_macro_scores_match_the_closed_form_of_a_known_confusion():
    true = [0, 0, 0, 1, 1, 2]
    predicted = [0, 0, 1, 1, 2, 2]
    # Per class (precision, recall): 0: (2/2, 2/3), 1: (1/2, 1/2), 2: (1/2, 1/1); F1 = 2PR / (P + R).
    per_class = [(1.0, 2 / 3), (0.5, 0.5), (0.5, 1.0)]
    f1s = [2 * p * r / (p + r) for p, r in per_class]
    scores = recognition_scores(true, predicted)
    assert scores["top1"] == pytest.approx(4 / 6, abs=1e-4)
    assert scores["precision"] == pytest.approx(statistics.fmean(p for p, _ in per_class), abs=1e-4)
    assert scores["recall"] == pytest.approx(statistics.fmean(r for _, r in per_class), abs=1e-4)
    assert scores["f1"] == pytest.approx(statistics.fmean(f1s), abs=1e-4)
    # A class never predicted counts with precision 0; a predicted class the test lacks is only a miss.
    assert recognition_scores([0, 0, 1, 1], [0, 0, 0, 0]) == {
        "top1": 0.5,
        "precision": 0.25,
        "recall": 0.5,
        "f1": pytest.approx(1 / 3, abs=1e-4),
    }
    assert recognition_scores([0, 0, 1, 1], [0, 7, 1, 1]) == {
        "top1": 0.75,
        "precision": 1.0,
        "recall": 0.75,
        "f1": pytest.approx((2 / 3 + 1) / 2, abs=1e-4),
    }


def test_shots_are_distinct_images_of_each_class_and_too_many_are_refused():
    labels = [0, 1, 0, 2, 1, 0, 2, 2, 1, 0]
    chosen = draw_shots(labels, 3, seed=4)
    assert len(set(chosen)) == 9 and Counter(labels[p] for p in chosen) == {0: 3, 1: 3, 2: 3}
    assert draw_shots(labels, 3, seed=4) == chosen and draw_shots(labels, 2, seed=5) != draw_shots(labels, 2, seed=6)
    with pytest.raises(
        ConfigError,
        match=r"--shots 4: class 'edge' \(1\) has only 3 real training images in the "
        r"run's split; give --shots 3 or fewer",
    ):
        draw_shots(labels, 4, seed=0, class_names=CLASSES)


def test_the_label_conditioner_is_found_or_refused():
    assert label_conditioner_index(["visual", "label", "text"], ["visual", "label", "text_scratch"], None) == 1
    with pytest.raises(
        ConfigError,
        match=r"this run's generator has no label conditioner \(0:visual \(reads "
        r"'visual'\), 1:text_scratch \(reads 'text'\)\); .*--scene label-to-touch",
    ):
        label_conditioner_index(["visual", "text"], ["visual", "text_scratch"], None)
    with pytest.raises(ConfigError, match="--conditioner 0 \\(visual\\) reads samples' 'visual', not 'label'"):
        label_conditioner_index(["visual", "label"], ["visual", "label"], 0)


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--shots", "50"], "--shots 50: class "),
        (["--conditioner", "1"], "--conditioner 1: this generator has conditioners 0..0 (0:label (reads 'label'))"),
        (["--generated-weight", "0"], "argument --generated-weight: 0: must be a finite number > 0"),
        (["--generated-weight", "nan"], "must be a finite number > 0"),
        (["--generated-weight", "1", "1.0"], "--generated-weight 1 1: each weight once"),
        (["--best-of", "65"], "--best-of 65: give an integer in [1, 64] (1: plain sampling)"),
    ],
)
def test_bad_requests_are_one_line_errors(label_run, tmp_path, capsys, flags, message):
    code = main(
        [
            "--no-progress",
            "evaluate",
            "downstream",
            "--run",
            str(label_run),
            "--out",
            str(tmp_path / "x"),
            "--feature-size",
            "32",
            *flags,
        ]
    )
    error = capsys.readouterr().err
    assert code == 2 and message in error and len(error.strip().splitlines()) == 1
    assert not (tmp_path / "x" / "downstream.json").exists()


def _folder_run(label_run, folder, dataset):
    """A copy of ``label_run`` whose dataset block is ``dataset`` (the trained models unchanged)."""
    shutil.copytree(label_run, folder)
    config = json.loads((folder / "config.json").read_text())
    config["data"]["dataset"] = dataset
    (folder / "config.json").write_text(json.dumps(config))
    return folder


def test_a_run_on_a_class_folder_works_and_an_unlabelled_one_is_refused(label_run, tmp_path, capsys, host):
    dataset, _ = _run_dataset(label_run, host)
    root = tmp_path / "frames"
    for index in range(len(dataset)):
        sample = dataset[index]
        save_png(sample["tactile"], root / CLASSES[sample["label"]] / f"{index:03d}.png")
    folder_run = _folder_run(
        label_run, tmp_path / "folder_run", {"name": "image_folder", "root": str(root), "class_names": CLASSES}
    )
    out = tmp_path / "folder_out"
    assert (
        main(
            [
                "--no-progress",
                "evaluate",
                "downstream",
                "--run",
                str(folder_run),
                "--out",
                str(out),
                "--seeds",
                "0",
                "--shots",
                "1",
                "--generated-per-class",
                "1",
                "--feature-size",
                "32",
            ]
        )
        == 0
    )
    result = json.loads((out / "downstream.json").read_text())
    assert result["dataset"] == "image_folder" and {row["arm"] for row in result["rows"]} == set(ARMS)
    assert result["test_images"] + result["real_train_images"] == 36

    (root / "list.csv").write_text(
        "path,label\n" + "".join(f"{p.relative_to(root).as_posix()},\n" for p in sorted(root.rglob("*.png")))
    )
    unlabelled = _folder_run(
        label_run, tmp_path / "unlabelled_run", {"name": "image_folder", "root": str(root), "csv": "list.csv"}
    )
    capsys.readouterr()
    assert main(["evaluate", "downstream", "--run", str(unlabelled), "--out", str(tmp_path / "y")]) == 2
    assert "the run's dataset (image_folder) has no class labels" in capsys.readouterr().err


def _blobs(seed, rows_per_class=6, classes=3, width=5):
    """Separable-ish labelled features: a class mean plus unit noise."""
    draw = torch.Generator().manual_seed(seed)
    means = torch.randn(classes, width, generator=draw) * 2
    labels = [label for label in range(classes) for _ in range(rows_per_class)]
    return means[labels] + torch.randn(len(labels), width, generator=draw), labels


def test_a_whole_sample_weight_is_the_row_repeated():
    """Independent reference: weight 2 on a row must fit what the row given twice fits (weighted
    standardization and loss both), and weight 1 must be the unweighted fit."""
    features, labels = _blobs(0)
    probe, _ = _blobs(1)
    weight = torch.ones(len(labels), dtype=torch.float64)
    weight[::4] = 2.0
    weighted = RealImageClassifier(features, labels, seed=0, sample_weight_N=weight)
    repeat = [index for index in range(len(labels)) for _ in range(int(weight[index]))]
    repeated = RealImageClassifier(features[repeat], [labels[i] for i in repeat], seed=0)
    fitted, reference = weighted.model[-1], repeated.model[-1]
    assert torch.tensor(fitted.coef_) == pytest.approx(torch.tensor(reference.coef_), abs=1e-4)
    assert weighted.model[0].mean_ == pytest.approx(repeated.model[0].mean_, abs=1e-10)
    assert weighted.model[0].scale_ == pytest.approx(repeated.model[0].scale_, abs=1e-10)
    plain = RealImageClassifier(features, labels, seed=0)
    ones = RealImageClassifier(features, labels, seed=0, sample_weight_N=torch.ones(len(labels)))
    assert torch.tensor(ones.model[-1].coef_) == pytest.approx(torch.tensor(plain.model[-1].coef_), abs=1e-8)
    assert ones.predict(probe) == plain.predict(probe)
    with pytest.raises(ValueError, match="3 sample weights for 18 rows"):
        RealImageClassifier(features, labels, sample_weight_N=[1.0, 1.0, 1.0])


def test_the_generated_weight_falls_on_the_generated_rows_only():
    """``train_and_test`` at generated weight 2 must score as the real rows once and the generated
    rows (those without a dataset index, after the real ones) twice."""
    real_features, labels = _blobs(2, rows_per_class=2)
    generated_features, generated_labels = _blobs(3, rows_per_class=4)
    test_features, test_labels = _blobs(4, rows_per_class=10)
    real = LabelledFeatures(real_features, labels, list(range(len(labels))))
    generated = LabelledFeatures(generated_features, generated_labels, [])
    test = LabelledFeatures(test_features, test_labels, [])
    doubled = LabelledFeatures.join(real, generated, generated)
    weighted = train_and_test(LabelledFeatures.join(real, generated), test, 0, generated_weight=2.0)
    assert weighted == train_and_test(doubled, test, 0)
    # Weighting the real rows twice instead is another fit: the weight must land where it is meant to.
    real_doubled = LabelledFeatures.join(real, real, generated)
    assert weighted[1] != train_and_test(real_doubled, test, 0)[1]
    assert train_and_test(LabelledFeatures.join(real, generated), test, 0, generated_weight=1.0) == train_and_test(
        LabelledFeatures.join(real, generated), test, 0
    )


def test_each_generated_weight_is_its_own_arm_on_the_same_images(label_run, tmp_path, monkeypatch):
    from vqtouch.plugins.experiments import downstream

    fits = []

    def recording(train, test, seed, generated_weight=1.0):
        fits.append((len(train.labels), len(train.indices), generated_weight))
        return train_and_test(train, test, seed, generated_weight)

    monkeypatch.setattr(downstream, "train_and_test", recording)
    out = tmp_path / "weights"
    flags = ["--seeds", "0", "--shots", "2", "--generated-per-class", "2", "--feature-size", "32"]
    args = ["--no-progress", "evaluate", "downstream", "--run", str(label_run), "--out", str(out), *flags]
    assert main([*args, "--generated-weight", "1", "0.25"]) == 0
    # (rows, rows with a dataset index, weight) of each fit: generated, few, the two mixed, ceiling,
    # the two reconstruction arms, background.
    assert fits == [
        (6, 0, 1.0),
        (6, 6, 1.0),
        (12, 6, 1.0),
        (12, 6, 0.25),
        (27, 27, 1.0),
        (6, 6, 1.0),
        (12, 12, 1.0),
        (6, 0, 1.0),
    ]
    result = json.loads((out / "downstream.json").read_text())
    light = mixed_arm(0.25)
    assert light == "real few + generated (weight 0.25)" and result["generated_weights"] == [1.0, 0.25]
    assert [row["arm"] for row in result["rows"]] == [
        GENERATED,
        FEW,
        FEW_AND_GENERATED,
        light,
        CEILING,
        RECONSTRUCTED,
        FEW_AND_RECONSTRUCTED,
        ARMS[-1],
    ]
    by_arm = {row["arm"]: row for row in result["rows"]}
    assert by_arm[light]["generated_weight"] == 0.25 and by_arm[FEW_AND_GENERATED]["generated_weight"] == 1.0
    assert by_arm[light]["real_indices"] == by_arm[FEW_AND_GENERATED]["real_indices"] == by_arm[FEW]["real_indices"]
    assert by_arm[light]["train_images"] == by_arm[FEW_AND_GENERATED]["train_images"] == 12
    assert "generated_weight" not in by_arm[FEW] and light in result["confusion"]["matrices"]
    markdown = (out / "downstream.md").read_text()
    assert f"| {light} | 2 | 2 |" in markdown and "each generated one weighing W against 1" in markdown


def test_through_the_tokenizer_the_classifiers_see_reconstructions(label_run, tmp_path, monkeypatch, host):
    """Independent reference: each classifier's real training rows, the held-out rows and the no-contact
    rows must be the features of ``decode_codes(encode_codes(image))``, not of the image as read."""
    from vqtouch.plugins.utils.splits import experiment_split
    from vqtouch.plugins.evaluation.contact import dataset_background
    from vqtouch.plugins.experiments import downstream
    from vqtouch.plugins.generator import load_pipeline

    fits = []

    def recording(train, test, seed, generated_weight=1.0):
        fits.append((train, test))
        return train_and_test(train, test, seed, generated_weight)

    monkeypatch.setattr(downstream, "train_and_test", recording)
    out = tmp_path / "decoded"
    flags = ["--seeds", "0", "--shots", "2", "--generated-per-class", "2", "--feature-size", "32"]
    args = ["--no-progress", "evaluate", "downstream", "--run", str(label_run), "--out", str(out), *flags]
    assert main([*args, "--through-tokenizer"]) == 0

    dataset, config = _run_dataset(label_run, host)
    tokenizer = load_pipeline(label_run, host=host).tokenizer
    metric = Assembly(config, host).build("metric", {"name": "fd_effnetlite0", "image_size": 32})

    def features(images_N3HW, decoded):
        with torch.no_grad():
            if decoded:
                images_N3HW = tokenizer.decode_codes(tokenizer.encode_codes(images_N3HW))
            return metric.pooled_features(images_N3HW.float()).float()

    def of_dataset(indices, decoded):
        return features(torch.stack([dataset[i]["tactile"] for i in indices]), decoded)

    (
        (generated, test),
        (few, _),
        (mixed, _),
        (ceiling, _),
        (reconstructed, _),
        (few_and_reconstructed, _),
        (
            background,
            _,
        ),
    ) = fits
    result = json.loads((out / "downstream.json").read_text())
    assert test.indices == result["test_indices"] and len(ceiling.indices) == 27 and len(few.indices) == 6
    for rows in (test, few, ceiling, reconstructed):
        assert torch.allclose(rows.features_NF, of_dataset(rows.indices, True), atol=1e-4)
        assert not torch.allclose(rows.features_NF, of_dataset(rows.indices, False), atol=1e-3)
    assert torch.equal(mixed.features_NF[:6], few.features_NF)
    assert torch.equal(mixed.features_NF[6:], generated.features_NF)
    assert torch.equal(few_and_reconstructed.features_NF, torch.cat([few.features_NF, reconstructed.features_NF]))
    train_split, _ = experiment_split(dataset, config.data, config.seed)
    no_contact, _ = dataset_background(train_split, tuple(dataset[0]["tactile"].shape[-2:]))
    assert torch.allclose(background.features_NF, features(no_contact[None], True).expand(6, -1), atol=1e-4)
    assert result["real_images"] == "the tokenizer's reconstructions"
    assert "passed through the run's tokenizer first (--through-tokenizer)" in (out / "downstream.md").read_text()


def test_others_are_drawn_per_class_outside_the_excluded_and_by_seed():
    labels = [0] * 6 + [1] * 3 + [2] * 5
    excluded = [0, 1, 6, 9]
    drawn = draw_others(labels, 3, seed=4, exclude=excluded)
    assert len(drawn) == len(set(drawn)) and not set(drawn) & set(excluded)
    # Class 1 has two others: both are taken, the other classes give three each.
    assert Counter(labels[p] for p in drawn) == {0: 3, 1: 2, 2: 3}
    assert draw_others(labels, 3, seed=4, exclude=excluded) == drawn
    assert any(draw_others(labels, 3, seed=s, exclude=excluded) != drawn for s in range(5, 10))
    # The reconstructions' draw has its own stream: the shots of the same seed are not its first picks.
    assert draw_others(labels, 2, seed=0, exclude=[]) != draw_shots(labels, 2, 0)


def test_the_reconstruction_arms_are_round_trips_of_other_training_images(label_run, tmp_path, monkeypatch, host):
    """Independent reference: the reconstruction arms' rows must be the features of
    ``decode_codes(encode_codes(image))`` of real training images of the run's split, two per class,
    none of them a shot of the same seed or a held-out image, with the real few before them."""
    from vqtouch.plugins.experiments import downstream
    from vqtouch.plugins.generator import load_pipeline

    fits = []

    def recording(train, test, seed, generated_weight=1.0):
        fits.append(train)
        return train_and_test(train, test, seed, generated_weight)

    monkeypatch.setattr(downstream, "train_and_test", recording)
    out = tmp_path / "reconstructed"
    assert main(["--no-progress", "evaluate", "downstream", "--run", str(label_run), "--out", str(out), *FAST]) == 0
    result = json.loads((out / "downstream.json").read_text())
    dataset, config = _run_dataset(label_run, host)
    train, held_out = split_dataset(dataset, config.data.val_fraction, config.seed)
    tokenizer = load_pipeline(label_run, host=host).tokenizer
    metric = Assembly(config, host).build("metric", {"name": "fd_effnetlite0", "image_size": 32})

    def of_dataset(indices, decoded):
        images_N3HW = torch.stack([dataset[i]["tactile"] for i in indices]).float()
        with torch.no_grad():
            if decoded:
                images_N3HW = tokenizer.decode_codes(tokenizer.encode_codes(images_N3HW))
            return metric.pooled_features(images_N3HW.float()).float()

    per_seed = len(ARMS)
    drawn = []
    for seed_index, seed in enumerate((0, 1)):
        fitted = dict(zip(ARMS, fits[seed_index * per_seed : (seed_index + 1) * per_seed]))
        rows = {row["arm"]: row for row in result["rows"] if row["seed"] == seed}
        reconstructed, few = fitted[RECONSTRUCTED], fitted[FEW]
        assert reconstructed.indices == rows[RECONSTRUCTED]["real_indices"]
        assert Counter(dataset[i]["label"] for i in reconstructed.indices) == {0: 2, 1: 2, 2: 2}
        assert set(reconstructed.indices) <= set(train.indices)
        assert not set(reconstructed.indices) & (set(held_out.indices) | set(few.indices))
        assert torch.allclose(reconstructed.features_NF, of_dataset(reconstructed.indices, True), atol=1e-4)
        assert not torch.allclose(reconstructed.features_NF, of_dataset(reconstructed.indices, False), atol=1e-3)
        mixed = fitted[FEW_AND_RECONSTRUCTED]
        assert torch.equal(mixed.features_NF, torch.cat([few.features_NF, reconstructed.features_NF]))
        assert mixed.labels == few.labels + reconstructed.labels
        assert rows[FEW_AND_RECONSTRUCTED]["real_per_class"] == 2 and rows[RECONSTRUCTED]["real_per_class"] == 0
        drawn.append(set(reconstructed.indices))
    assert drawn[0] != drawn[1]  # the seed draws them
    assert result["reconstruction_shortfall"] == {}
    assert "what a generator that reproduced its training images would give" in (out / "downstream.md").read_text()


def test_best_of_reaches_the_sampler_with_each_row_s_own_label(label_run, tmp_path, monkeypatch):
    from vqtouch.plugins.experiments import downstream

    calls = []
    real_sample_images = downstream.sample_images

    def recording(*args, **kwargs):
        calls.append((kwargs["best_of"], kwargs["labels_B"].tolist(), args[5]))
        return real_sample_images(*args, **kwargs)

    monkeypatch.setattr(downstream, "sample_images", recording)
    out = tmp_path / "best_of"
    flags = ["--seeds", "0", "--shots", "2", "--generated-per-class", "2", "--feature-size", "32", "--batch-size", "4"]
    args = ["--no-progress", "evaluate", "downstream", "--run", str(label_run), "--out", str(out), *flags]
    assert main([*args, "--best-of", "3"]) == 0
    # Class-major rows in batches of 4: each row's label is the class it is generated for.
    assert calls == [(3, [0, 0, 1, 1], [0, 1, 2, 3]), (3, [2, 2], [4, 5])]
    result = json.loads((out / "downstream.json").read_text())
    assert result["best_of"] == 3 and result["best_of_rank"] == "judge"
    assert "best of 3 candidates by a classifier of code grids" in (out / "downstream.md").read_text()
    posterior = tmp_path / "posterior"
    again = ["--no-progress", "evaluate", "downstream", "--run", str(label_run), "--out", str(posterior), *flags]
    assert main([*again, "--best-of", "3", "--best-of-rank", "posterior"]) == 0
    result = json.loads((posterior / "downstream.json").read_text())
    assert result["best_of_rank"] == "posterior"
    assert "best of 3 candidates by the generator's own class posterior" in (posterior / "downstream.md").read_text()


def test_a_class_with_too_few_other_images_is_reported_short(label_run, tmp_path, host):
    dataset, config = _run_dataset(label_run, host)
    train, _ = split_dataset(dataset, config.data.val_fraction, config.seed)
    per_class = Counter(int(dataset[i]["label"]) for i in train.indices)
    asked = max(per_class.values()) - 2 + 1  # one more than the best-stocked class has beside 2 shots
    out = tmp_path / "short"
    flags = ["--seeds", "0", "--shots", "2", "--generated-per-class", str(asked), "--feature-size", "32"]
    assert main(["--no-progress", "evaluate", "downstream", "--run", str(label_run), "--out", str(out), *flags]) == 0
    result = json.loads((out / "downstream.json").read_text())
    assert result["reconstruction_shortfall"] == {str(label): asked - (count - 2) for label, count in per_class.items()}
    row = next(row for row in result["rows"] if row["arm"] == RECONSTRUCTED)
    assert row["train_images"] == sum(count - 2 for count in per_class.values())
    assert "Classes with fewer other training images than that" in (out / "downstream.md").read_text()


def test_a_plugin_ranker_is_named_in_the_notes_and_a_built_in_one_described():
    from vqtouch.plugins.experiments.downstream_report import _settings_notes

    result = {"best_of": 4, "background": "", "classes_without_training_images": [], "best_of_rank": "last"}
    notes = " ".join(_settings_notes(result))
    assert "best of 4 candidates by the `last` ranker" in notes
    notes = " ".join(_settings_notes({**result, "best_of_rank": "consensus"}))
    assert "by the candidate whose contact centre the others agree on most" in notes

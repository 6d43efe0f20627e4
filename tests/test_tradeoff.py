"""`vqtouch tradeoff generator` and the distribution scores of generated images in the generator's
scoring (`generation.json`, `vqtouch evaluate generation`), on a tiny trained run."""

import json
import random
import shutil

import pytest
from generator_runs import train_args

from vqtouch.plugins.cli.app import main
from vqtouch.plugins.generator.tradeoff import pareto_front, setting_label, sweep_settings

#: The run's own fd_effnetlite0 metric at 32 px: the distribution scores take their features from it.
FD_32 = 'metrics=[{"name": "psnr"}, {"name": "fd_effnetlite0", "image_size": 32}]'
DISTRIBUTION_KEYS = {"fd_effnetlite0", "classifier_accuracy", "real_classifier_accuracy", "classifier_train_images"}


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny label-to-touch run whose stage also scored the distribution."""
    out = tmp_path_factory.mktemp("tradeoff") / "run"
    assert main(train_args(out, FD_32, "generator.distribution=true")) == 0
    return out


def test_the_stage_scores_the_distribution_when_asked(trained):
    result = json.loads((trained / "generation.json").read_text())
    assert DISTRIBUTION_KEYS <= set(result)
    for prefix in ("retrieval_", "background_", "class_mean_", "ceiling_"):
        assert isinstance(result[prefix + "fd_effnetlite0"], float), prefix
        assert 0 <= result[prefix + "classifier_accuracy"] <= 1, prefix
    assert result["classifier_train_images"] == result["train_samples"] == 18
    assert 0 <= result["classifier_accuracy"] <= 1 and result["fd_effnetlite0"] > 0


def test_evaluate_generation_scores_the_distribution_unless_told_not_to(trained, capsys):
    args = ["evaluate", "generation", "--run", str(trained), "--n", "3", "--steps", "2"]
    written = trained / "evaluation_generation_step-00000006_posterior_2.json"
    assert main(args) == 0
    scored = json.loads(written.read_text())
    assert DISTRIBUTION_KEYS <= set(scored) and "retrieval_classifier_accuracy" in scored
    assert main([*args, "--no-distribution"]) == 0
    plain = json.loads(written.read_text())
    assert not {key for key in plain if "classifier" in key}
    # The run's fd_effnetlite0 metric still scores each image set, and gives the distribution's number
    # (the same quantity; the metric's eigen-decompositions round differently).
    for key in ("fd_effnetlite0", "retrieval_fd_effnetlite0", "background_fd_effnetlite0"):
        assert plain[key] == pytest.approx(scored[key], rel=1e-4, abs=1e-3), key
    # The same generated images either way.
    assert {key: value for key, value in scored.items() if key in plain and "fd_" not in key} == {
        key: value for key, value in plain.items() if "fd_" not in key
    }


def independent_front(costs, qualities, higher):
    """A point is on the front iff no other point is both cheaper and better."""
    better = (lambda a, b: a > b) if higher else (lambda a, b: a < b)
    return sorted(
        (
            i
            for i in range(len(costs))
            if not any(costs[j] < costs[i] and better(qualities[j], qualities[i]) for j in range(len(costs)))
        ),
        key=lambda i: costs[i],
    )


@pytest.mark.parametrize("higher", [True, False])
@pytest.mark.parametrize("seed", range(5))
def test_the_pareto_front_against_an_independent_check(higher, seed):
    rng = random.Random(seed)
    costs = rng.sample(range(1, 1000), 25)  # distinct costs and qualities: no ties
    qualities = [value / 7 for value in rng.sample(range(1, 1000), 25)]
    assert pareto_front(costs, qualities, higher) == independent_front(costs, qualities, higher)


def test_the_pareto_front_on_hand_built_points():
    costs = [1.0, 2.0, 3.0, 4.0, 0.5]
    psnr = [20.0, 25.0, 24.0, 30.0, None]  # the cheapest has no score: on no front
    assert pareto_front(costs, psnr, higher_is_better=True) == [0, 1, 3]
    assert pareto_front(costs, [5.0, 3.0, 1.0, 2.0, 9.0], higher_is_better=False) == [4, 0, 1, 2]
    assert pareto_front([1.0, 1.0, 2.0], [3.0, 4.0, 4.0]) == [1]  # ties: at least as cheap and as good, better in one


def test_the_settings_vary_one_knob_at_a_time_or_all():
    knobs = dict(
        steps=[100, 50, 25, 10, 5],
        samplers=["posterior", "purity", "confidence"],
        guidance=[1.0, 3.0],
        precisions=["fp32", "bf16"],
    )
    settings = sweep_settings(**knobs)
    assert settings[0] == {"sampler": "posterior", "steps": 100, "guidance": 1.0, "precision": "fp32"}
    assert [s["steps"] for s in settings] == [100, 50, 25, 10, 5, 25, 25, 25, 25]
    assert [(s["sampler"], s["guidance"], s["precision"]) for s in settings[5:]] == [
        ("purity", 1.0, "fp32"),
        ("confidence", 1.0, "fp32"),
        ("posterior", 3.0, "fp32"),
        ("posterior", 1.0, "bf16"),
    ]
    assert len(sweep_settings(**knobs, grid=True)) == 5 * 3 * 2 * 2
    assert len(sweep_settings(**{**knobs, "guidance": [1.0, 1.0]})) == 8  # duplicates dropped


def test_tradeoff_generator_writes_the_table_the_json_and_the_pareto_plot(trained, tmp_path, capsys):
    out = tmp_path / "trade"
    assert (
        main(
            [
                "tradeoff",
                "generator",
                "--run",
                str(trained),
                "--out",
                str(out),
                "--n",
                "3",
                "--rounds",
                "2",
                "--steps",
                "4",
                "2",
                "--samplers",
                "posterior",
                "confidence",
                "--guidance",
                "1",
                "2",
                "--precisions",
                "fp32",
                "bf16",
                "--batch-size",
                "2",
                "--threads",
                "1",
            ]
        )
        == 0
    )
    captured = capsys.readouterr()
    assert captured.err.count("[round ") == 2 * 5  # progress per setting and round
    result = json.loads((out / "tradeoff.json").read_text())
    rows = result["settings"]
    assert [row["label"] for row in rows] == [
        "posterior 4",
        "posterior 2",
        "confidence 2",
        "posterior 2 g2",
        "posterior 2 bf16",
    ]
    assert result["n"] == 3 and result["rounds"] == 2 and result["threads"] == 1 and result["feature_size"] == 32
    assert rows[0]["cost"] == 1.0 and all(len(row["seconds"]) == 2 and row["reproducible"] for row in rows)
    for row in rows:
        assert {"ssim", "psnr", "contact_psnr", "contact_centroid_error_px", "img_per_s"} <= set(row)
        assert {"fd_effnetlite0", "classifier_accuracy"} <= set(row)
    assert 0 <= result["reference"]["real_classifier_accuracy"] <= 1
    qualities = {"contact_psnr": True, "contact_centroid_error_px": False, "fd_effnetlite0": False}
    for key, higher in (qualities | {"classifier_accuracy": True}).items():
        costs, values = [row["seconds_per_image"] for row in rows], [row[key] for row in rows]
        assert {i for i, row in enumerate(rows) if key in row["pareto"]} == set(pareto_front(costs, values, higher))
    table = (out / "tradeoff.md").read_text().splitlines()
    assert table[0].startswith("Generator trade-off: run ") and "n = 3 held-out" in table[0]
    assert "conditioner 0:label" in table[0] and result["conditioner"] == "0:label"
    header = next(line for line in table if line.startswith("| sampler"))
    assert header.split(" | ").index("centroid px") == header.split(" | ").index("contact PSNR dB") + 1
    assert "threads 1" in table[0] and "rounds 2" in table[0] and "device cpu" in table[0]
    body = [line for line in table if line.startswith("| ") and not line.startswith("| sampler")]
    assert len(body) == len(rows) and body[0].startswith("| posterior | 4 | 1 | fp32 |")
    assert (out / "pareto.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "pareto.png" in captured.out
    # A row's scores are those `vqtouch evaluate generation` gives the same setting (same conditions and seeds).
    for row in (rows[0], rows[3]):
        assert (
            main(
                [
                    "evaluate",
                    "generation",
                    "--run",
                    str(trained),
                    "--n",
                    "3",
                    "--steps",
                    str(row["steps"]),
                    "--guidance",
                    str(row["guidance"]),
                    "--metrics",
                    "ssim,psnr",
                    "--no-distribution",
                ]
            )
            == 0
        )
        name = f"evaluation_generation_step-00000006_posterior_{row['steps']}.json"
        evaluated = json.loads((trained / name).read_text())
        for key in ("ssim", "psnr", "contact_psnr", "contact_centroid_error_px"):
            assert row[key] == pytest.approx(evaluated[key], abs=2e-4), (row["label"], key)


def test_best_of_is_a_knob_of_the_sweep_only_when_asked():
    knobs = dict(steps=[25], samplers=["posterior"], guidance=[2.0], precisions=["fp32"])
    assert all("best_of" not in setting for setting in sweep_settings(**knobs))
    settings = sweep_settings(**knobs, best_of=[1, 4, 8])
    assert [s["best_of"] for s in settings] == [1, 4, 8] and {s["guidance"] for s in settings} == {2.0}
    assert [setting_label(s) for s in settings] == ["posterior 25 g2", "posterior 25 g2 best4", "posterior 25 g2 best8"]


def test_tradeoff_times_best_of_k_beside_one_draw_with_a_fair_classifier(trained, tmp_path, capsys):
    out = tmp_path / "best"
    args = ["tradeoff", "generator", "--run", str(trained), "--out", str(out), "--n", "3", "--rounds", "1"]
    args += ["--steps", "3", "--samplers", "posterior", "--guidance", "1", "--precisions", "fp32"]
    assert main([*args, "--best-of", "1", "3", "--classifier-on", "reconstructions", "--threads", "1"]) == 0
    capsys.readouterr()
    result = json.loads((out / "tradeoff.json").read_text())
    rows = result["settings"]
    assert [row["best_of"] for row in rows] == [1, 3] and result["classifier_trained_on"].endswith(
        "reconstructions of the training images"
    )
    # Three candidates, each scored under every class, cost more than one draw.
    assert rows[1]["seconds_per_image"] > rows[0]["seconds_per_image"]
    # The best-of row is what `vqtouch evaluate generation --best-of 3` draws on the same conditions.
    scored = tmp_path / "scored"
    evaluate = ["evaluate", "generation", "--run", str(trained), "--n", "3", "--steps", "3", "--guidance", "1"]
    assert main([*evaluate, "--metrics", "ssim,psnr", "--no-distribution", "--best-of", "3", "--out", str(scored)]) == 0
    evaluated = json.loads((scored / "generation.json").read_text())["by_conditioner"]["0:label"]
    assert evaluated["best_of"] == 3 and rows[1]["psnr"] == pytest.approx(evaluated["psnr"], abs=2e-4)
    assert rows[1]["psnr"] != pytest.approx(rows[0]["psnr"], abs=2e-4)
    # Fitted on reconstructions, the classifier is referred to the tokenizer's ceiling, not to sharp images.
    reference = result["reference"]
    assert "real_classifier_accuracy" not in reference and 0 <= reference["ceiling_classifier_accuracy"] <= 1
    assert reference["ceiling_contact_psnr"] == pytest.approx(evaluated["ceiling_contact_psnr"], abs=2e-4)
    table = (out / "tradeoff.md").read_text()
    assert "| best of |" in table and "| posterior | 3 | 1 | fp32 | 3 |" in table
    assert "classifier on the reconstructions of the training images" in table.splitlines()[0]


@pytest.mark.parametrize(
    "args, message",
    [
        (
            ["--steps", "4", "--samplers", "posterior", "nope"],
            "unknown sampler 'nope'; available: confidence, posterior, purity",
        ),
        (["--steps", "4", "0"], "argument --steps: 0: must be an integer >= 1"),
        (["--steps", "21"], "--steps 21: steps must be an integer in [1, 20]"),
        (["--steps", "4", "--guidance=-1"], "argument --guidance: -1: must be a finite number in [0, 1000]"),
        (["--steps", "4", "--precisions", "fp16"], "--precisions fp16: expected fp32 or bf16"),
        (["--steps", "4", "--best-of", "1", "65"], "--best-of 65: give an integer in [1, 64]"),
        (["--steps", "4", "--conditioner", "1"], "--conditioner 1 is none of this generator's conditioners (0:label)"),
    ],
)
def test_tradeoff_errors_are_one_line(trained, tmp_path, capsys, args, message):
    capsys.readouterr()
    assert main(["tradeoff", "generator", "--run", str(trained), "--out", str(tmp_path / "t"), *args]) == 2
    err = capsys.readouterr().err
    assert err.startswith("vqtouch: error: ") and err.count("\n") == 1 and message in err, err
    assert not (tmp_path / "t").exists()


def test_tradeoff_of_a_run_without_a_trained_generator_says_so(trained, tmp_path, capsys):
    tokenizer_only = tmp_path / "tok"
    shutil.copytree(trained, tokenizer_only)
    shutil.rmtree(tokenizer_only / "checkpoints" / "generator")
    capsys.readouterr()
    assert main(["tradeoff", "generator", "--run", str(tokenizer_only), "--out", str(tmp_path / "t")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"vqtouch: error: no trained generator in {tokenizer_only}") and err.count("\n") == 1, err
    assert "vqtouch train generator" in err

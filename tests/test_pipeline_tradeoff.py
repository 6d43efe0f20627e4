"""`vqtouch evaluate tradeoff` at toy size: every knob value once per seed, costs relative
to the same seed's baseline, Pareto flags against a brute-force check of domination, the tokenizer
scores as the tokenizer stage wrote them, interleaved timing rounds, and one-line errors."""

import json
import statistics
from collections import Counter

import pytest
import torch

from vqtouch.plugins.cli.app import main
from vqtouch.core.config import resolve_config
from vqtouch.plugins.training.precision import cpu_has_bf16_matrix_units
from vqtouch.plugins.experiments import pipeline_tradeoff as tradeoff
from vqtouch.plugins.experiments import pipeline_tradeoff_configs as configs
from vqtouch.plugins.experiments.pipeline_tradeoff_report import DRIFT

#: A tiny VQGAN tokenizer and generator at 32 px (tests/generator_runs.py's sizes); the encoder's
#: name first: selecting a plugin resets its options.
TINY = [
    "tokenizer.autoencoder.name=vqgan",
    "tokenizer.autoencoder.channels=16",
    "tokenizer.autoencoder.norm_groups=8",
    "tokenizer.autoencoder.channel_multipliers=[1,2]",
    "tokenizer.autoencoder.z_channels=16",
    "tokenizer.autoencoder.embed_dim=8",
    "tokenizer.quantizer.codebook_size=32",
    "data.image_size=32",
    "data.batch_size=4",
    "data.dataset.num_samples=16",
    "data.val_fraction=0.25",
    "tokenizer.loss.perceptual=none",
    "tokenizer.discriminator=null",
    'metrics=[{"name": "psnr"}, {"name": "ssim"}]',
    "generator.model.depth=1",
    "generator.model.width=32",
    "generator.model.num_steps=20",
    "generator.steps=4",
]
KNOBS = ["codebook=16,64", "downsampling", "steps=2", "sampler=confidence"]
SEEDS = (0, 1)
#: What ``precision: auto`` and ``generator.sample_precision: auto`` resolve to on this machine.
AUTO = "bf16" if cpu_has_bf16_matrix_units() else "fp32"
#: Every (part, knob, setting) the run must measure once per seed.
EXPECTED = {
    ("tokenizer", "baseline", f"off (vqgan), K = 32, 32 px, train {AUTO}, f = 2"),
    ("tokenizer", "codebook", "K = 16"),
    ("tokenizer", "codebook", "K = 64"),
    ("tokenizer", "downsampling", "f = 4"),
    ("tokenizer", "baseline", DRIFT),
    ("generator", "baseline", "posterior 4" + (" bf16" if AUTO == "bf16" else "")),
    ("generator", "steps", "2 steps"),
    ("generator", "sampler", "confidence"),
    ("generator", "baseline", DRIFT),
}


def tiny_args(out, *extra):
    args = ["--no-progress", "evaluate", "tradeoff", "--out", str(out)]
    for override in TINY:
        args += ["--set", override]
    return args + list(extra)


@pytest.fixture(scope="module")
def experiment(tmp_path_factory):
    out = tmp_path_factory.mktemp("pipeline_tradeoff") / "trade"
    threads = torch.get_num_threads()
    try:  # one thread: on a shared CPU, two spinning OpenMP threads per process cost 10x
        assert (
            main(
                tiny_args(
                    out,
                    "--seeds",
                    *map(str, SEEDS),
                    "--tokenizer-steps",
                    "2",
                    "--generator-steps",
                    "2",
                    "--rounds",
                    "2",
                    "--timing-steps",
                    "1",
                    "--n",
                    "3",
                    "--threads",
                    "1",
                    "--knobs",
                    *KNOBS,
                )
            )
            == 0
        )
    finally:
        torch.set_num_threads(threads)
    return out, json.loads((out / "tradeoff.json").read_text())


def test_every_knob_value_is_measured_once_per_seed_and_written(experiment):
    out, result = experiment
    for seed in SEEDS:
        measured = Counter((row["part"], row["knob"], row["setting"]) for row in result["rows"] if row["seed"] == seed)
        assert set(measured) == EXPECTED and set(measured.values()) == {1}, seed
    assert {(row["part"], row["knob"], row["setting"]) for row in result["summary"]} == EXPECTED
    assert all(row["seeds"] == len(SEEDS) for row in result["summary"])
    # The summary is the mean and spread over the seeds of the rows.
    rows = [row for row in result["rows"] if row["setting"] == "K = 16"]
    summary = next(row for row in result["summary"] if row["setting"] == "K = 16")
    for key in ("contact_ssim", "train_cost", "psnr"):
        assert summary[key] == pytest.approx(statistics.fmean(row[key] for row in rows), abs=1e-5)
        assert summary[f"{key}_std"] == pytest.approx(statistics.pstdev(row[key] for row in rows), abs=1e-5)
    assert result["front_quality"] == "contact_ssim" and result["seeds"] == list(SEEDS)
    markdown = (out / "tradeoff.md").read_text()
    table = [line for line in markdown.splitlines() if line.startswith("| tokenizer") or line.startswith("| generator")]
    assert len(table) == len(EXPECTED) and "| tokenizer | codebook | K = 16 |" in markdown
    assert "bg contact SSIM" in markdown and "Pareto front" in markdown
    assert (out / "tradeoff.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_costs_are_relative_to_the_same_seeds_baseline(experiment):
    _, result = experiment
    for seed in SEEDS:
        rows = [row for row in result["rows"] if row["seed"] == seed]
        for part, keys in (
            ("tokenizer", (("train_cost", "train_s_per_step"), ("inference_cost", "seconds_per_image"))),
            ("generator", (("inference_cost", "seconds_per_image"),)),
        ):
            members = [row for row in rows if row["part"] == part]
            base = members[0]
            assert base["knob"] == "baseline" and base["setting"] != DRIFT
            for row in members:
                for ratio, cost in keys:
                    assert row[cost] > 0
                    assert row[ratio] == pytest.approx(row[cost] / base[cost], rel=2e-3, abs=1e-4), (part, row["knob"])
                assert row["img_per_s"] == pytest.approx(1 / row["seconds_per_image"], rel=2e-3)


def dominated_brute_force(points):
    """Indices on the front: no other point is at least as cheap and at least as good and strictly
    better in one; of identical points only the first."""
    front = set()
    for i, (cost, quality) in enumerate(points):
        beaten = any(
            (c <= cost and q >= quality and (c < cost or q > quality)) or ((c, q) == (cost, quality) and j < i)
            for j, (c, q) in enumerate(points)
            if j != i
        )
        if not beaten:
            front.add(i)
    return front


def test_pareto_flags_agree_with_a_brute_force_check_of_the_written_rows(experiment):
    _, result = experiment
    summary = result["summary"]
    checked = 0
    for part, cost, name in (
        ("tokenizer", "train_cost", "training"),
        ("tokenizer", "inference_cost", "inference"),
        ("generator", "inference_cost", "generation"),
    ):
        contenders = [row for row in summary if row["part"] == part and row["setting"] != DRIFT]
        front = dominated_brute_force([(row[cost], row["contact_ssim"]) for row in contenders])
        assert {i for i, row in enumerate(contenders) if name in row["pareto"]} == front, name
        checked += len(contenders)
    assert checked == 4 + 4 + 3
    for row in summary:
        assert row["pareto_front"] == (", ".join(row["pareto"]) or "-")
        if row["setting"] == DRIFT:  # a timing of the baseline, not a contender
            assert row["pareto"] == [] and "contact_ssim" not in row


def test_tokenizer_rows_hold_the_scores_of_runs_trained_by_the_stage(experiment):
    _, result = experiment
    for row in (row for row in result["rows"] if row["part"] == "tokenizer" and row["setting"] != DRIFT):
        run = json.loads((tradeoff.Path(row["run"]) / "config.json").read_text())
        written = json.loads((tradeoff.Path(row["run"]) / "eval.json").read_text())
        assert written["step"] == 2 and run["seed"] == row["seed"]
        for key in ("ssim", "psnr", "contact_ssim", "contact_psnr", "background_contact_ssim", "codes_used"):
            assert row[key] == written[key], key
        assert row["background_contact_ssim"] > 0 and 0 < row["contact_fraction"] < 1
        tokenizer = run["tokenizer"]
        assert tokenizer["quantizer"]["codebook_size"] == (int(row["setting"][4:]) if row["knob"] == "codebook" else 32)
        multipliers = [1, 2, 2] if row["knob"] == "downsampling" else [1, 2]
        assert tokenizer["autoencoder"]["channel_multipliers"] == multipliers
        assert tokenizer["autoencoder"]["channels"] == 16 and run["data"]["image_size"] == 32
    generator = [row for row in result["rows"] if row["part"] == "generator" and row["setting"] != DRIFT]
    assert all(row["reproducible"] and "background_contact_ssim" in row for row in generator)


def test_each_sampling_setting_changes_one_knob_of_the_configured_one(experiment):
    _, result = experiment
    configured = {"sampler": "posterior", "steps": 4, "guidance": 1.0, "precision": AUTO}
    key_of = {"steps": "steps", "sampler": "sampler"}
    for row in (row for row in result["rows"] if row["part"] == "generator"):
        changed = {key: value for key, value in row["sampling"].items() if configured[key] != value}
        assert set(changed) == (set() if row["knob"] == "baseline" else {key_of[row["knob"]]}), row["setting"]


class FakeTimer:
    """Costs from a script, in the order asked; records who was timed when."""

    def __init__(self, name, costs, calls):
        self.name, self.costs, self.calls = name, iter(costs), calls

    def training_seconds_per_step(self):
        self.calls.append(self.name)
        return next(self.costs)

    def seconds_per_image(self):
        return 1.0


def test_timing_rounds_are_interleaved_with_the_baseline_first_and_last():
    calls = []
    # Warm-up first (discarded), then per round the baseline twice (first and last), the others once.
    baseline = FakeTimer("base", [99, 1.0, 1.2, 3.0, 1.4, 1.1, 5.0], calls)
    knob = FakeTimer("knob", [99, 5.0, 9.0, 6.0], calls)
    costs = tradeoff.time_tokenizers([baseline, knob], rounds=3, report=lambda line: None)
    assert calls == ["base", "knob"] + ["base", "knob", "base"] * 3
    assert [train for train, _ in costs] == [1.1, 6.0, 1.4]  # medians, not means


@pytest.mark.parametrize(
    "knobs, message",
    [
        (
            ["bogus"],
            "--knobs bogus: unknown knob 'bogus'; known knobs: deformable, codebook, resolution, precision, "
            "downsampling, steps, sampler, guidance, sampling-precision",
        ),
        (["codebook=32"], "--knobs codebook=32: K = 32 is the baseline's own value"),
        (["codebook=many"], "--knobs codebook=many: 'many': 'many' is not an integer"),
        (["downsampling=6"], "--knobs downsampling=6: '6': expected a power of two >= 2"),
        (["codebook", "codebook=8"], "--knobs codebook=8: the knob 'codebook' is given twice"),
        (["steps=50"], "--knobs steps=50: more sampling steps than the generator's 20 diffusion steps"),
        (["sampler=nope"], "nope"),
    ],
)
def test_bad_knobs_are_one_line_errors(tmp_path, capsys, knobs, message):
    assert main(tiny_args(tmp_path / "x", "--knobs", *knobs)) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("vqtouch: error: ") and message in err and "\n" not in err
    assert not (tmp_path / "x" / "runs").exists()  # refused before anything trained


def test_a_generator_knob_needs_a_scene_with_a_generator(tmp_path, capsys):
    assert main(["evaluate", "tradeoff", "reconstruction", "--out", str(tmp_path / "x"), "--knobs", "steps"]) == 2
    assert (
        "the steps knob is a generator knob, but the scene 'reconstruction' trains no generator"
        in capsys.readouterr().err
    )


def test_default_knob_values_derive_from_the_baseline(host):
    config = resolve_config("label-to-touch", host=host)
    tiny_dm_vqgan = resolve_config("label-to-touch", overrides=TINY[1:], host=host)
    knobs = configs.parse_knobs(None, config, host)
    other = "fp32" if AUTO == "bf16" else "bf16"  # the knob's default is the precision auto does not pick
    assert knobs == {
        "deformable": ["off"],
        "codebook": [128, 2048],
        "resolution": [128],
        "precision": [other],
        "downsampling": [8],
        "steps": [50, 12],
        "sampler": ["confidence", "purity"],
        "guidance": [3.0],
        "sampling-precision": [other],
    }
    # Scaled like the demo, the configured sampling steps (and so their defaults) are the demo's.
    assert configs.parse_knobs(["steps"], configs.scaled_config(config, host, full=False), host) == {"steps": [20, 5]}
    assert set(configs.parse_knobs(None, resolve_config("reconstruction", host=host), host)) == {
        "deformable",
        "codebook",
        "resolution",
        "precision",
        "downsampling",
    }
    # Deformable layers off: vqgan with every option the two encoders share.
    baseline = configs.baseline_config(tiny_dm_vqgan, host, tokenizer_steps=3, generator_steps=3, generator=True)
    variant = configs.variant_config(baseline, host, 5, "deformable", "off")
    shared = set(type(variant.tokenizer.autoencoder).model_fields) - {"name"}
    assert variant.tokenizer.autoencoder.name == "vqgan" and variant.seed == 5 and variant.stages == ["tokenizer"]
    assert {key: getattr(variant.tokenizer.autoencoder, key) for key in shared} == {
        key: getattr(baseline.tokenizer.autoencoder, key) for key in shared
    }
    assert baseline.tokenizer.train.steps == 3 == baseline.generator.train.steps and baseline.generator.num_samples == 0
    assert baseline.tokenizer.autoencoder.name == "dm_vqgan" and variant.tokenizer.autoencoder.channels == 16
    assert variant.tokenizer.autoencoder.z_channels == 16 and variant.tokenizer.autoencoder.embed_dim == 8
    assert configs.variant_config(baseline, host, 0, "downsampling", 8).tokenizer.autoencoder.channel_multipliers == (
        1,
        2,
        2,
        2,
    )

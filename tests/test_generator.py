"""The generator end to end: `vqtouch train generator`, `vqtouch generate`, the pipeline,
the code cache, exact resume, and the generator at numerical extremes."""

import json
import shutil

import pytest
import torch

from vqtouch.core import BuildContext, ConditionTokens, load_plugins
from vqtouch.plugins.cli.app import main
from vqtouch.plugins.testing import check_plugin

from generator_runs import TINY, train_args  # noqa: E402  (registered by conftest)

HOST = load_plugins(autoload=False)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny label-to-touch run: tokenizer (2 steps) then generator (6 steps)."""
    out = tmp_path_factory.mktemp("l2t") / "run"
    assert main(train_args(out)) == 0
    return out


def lines(run, stage="generator"):
    records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    return [r for r in records if r["stage"] == stage]


def test_train_generator_writes_its_run_and_scores_samples(trained):
    result = json.loads((trained / "generation.json").read_text())
    assert result["step"] == 6 and result["samples"] == 4 and result["sampler"] == "posterior"
    assert result["code_cache"]["cache"] in ("miss", "hit") and 0 < result["psnr"] < 100
    assert sorted(p.name for p in (trained / "checkpoints" / "generator").iterdir()) == [
        "step-00000003",
        "step-00000006",
    ]
    assert (trained / "samples.png").is_file()
    assert [r["step"] for r in lines(trained) if "loss" in r] == [1, 2, 3, 4, 5, 6]


def test_generate_is_deterministic_and_independent_of_the_batch(trained, tmp_path, capsys):
    def generate(out, *extra):
        assert (
            main(
                [
                    "generate",
                    "--run",
                    str(trained),
                    "--label",
                    "0",
                    "--label",
                    "3",
                    "--label",
                    "5",
                    "--n",
                    "3",
                    "--steps",
                    "3",
                    "--guidance",
                    "2",
                    "--truncation",
                    "0.9",
                    "--seed",
                    "7",
                    "--out",
                    str(out),
                    *extra,
                ]
            )
            == 0
        )
        return [(out / f"sample_{i:04d}.png").read_bytes() for i in range(3)]

    first = generate(tmp_path / "a")
    assert generate(tmp_path / "b") == first
    assert generate(tmp_path / "c", "--batch-size", "1") == first
    assert generate(tmp_path / "d", "--seed", "8") != first
    settings = json.loads((tmp_path / "a" / "generate.json").read_text())
    assert settings["values"] == ["0", "3", "5"] and settings["steps"] == 3 and settings["guidance"] == 2.0
    assert (tmp_path / "a" / "grid.png").is_file()


@pytest.mark.parametrize("sampler", ["posterior", "purity", "confidence"])
def test_the_python_pipeline_takes_every_sampler_and_class_names(trained, sampler):
    from vqtouch.plugins.generator import load_pipeline

    pipe = load_pipeline(trained, host=HOST)
    images = pipe(label=["sphere", 2], steps=3, sampler=sampler, seed=0)
    assert images.shape == (2, 3, 32, 32) and bool(torch.isfinite(images).all())
    assert float(images.min()) >= 0 and float(images.max()) <= 1
    assert torch.equal(images, pipe(label=["sphere", 2], steps=3, sampler=sampler, seed=0))


@pytest.mark.parametrize(
    "args, message",
    [
        (["--label", "blob"], "--label: unknown class 'blob'; available: "),
        (["--label", "99"], "--label 99: out of range; this run's classes are 0..11"),
        (["--visual", "photo.png"], "this generator was not trained with a 'visual' condition; it takes: label"),
        (["--label", "1", "--label", "2", "--n", "3"], "2 --label values for --n 3; give one value or --n values"),
        ([], "give exactly one kind of condition"),
        (["--label", "1", "--steps", "21"], "steps must be an integer in [1, 20]"),
    ],
)
def test_generate_errors_are_one_line(trained, tmp_path, capsys, args, message):
    capsys.readouterr()
    assert main(["generate", "--run", str(trained), *args, "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("vqtouch: error: ") and err.count("\n") == 1 and message in err, err


def test_a_second_run_reuses_the_cached_codes(trained, tmp_path):
    out = tmp_path / "again"
    assert main(train_args(out)) == 0
    cache = json.loads((out / "generation.json").read_text())["code_cache"]
    assert cache["cache"] == "hit"
    # The same tokenizer weights (trained with the same seed) and images: the cached codes are its codes.
    from safetensors.torch import load_file

    from vqtouch.plugins.generator.codes import encode_dataset
    from vqtouch.plugins.tokenizer import load_tokenizer
    from vqtouch.core import Assembly
    from vqtouch.plugins.runtime.run_dir import RunDir

    run = RunDir.open(out)
    tokenizer, _ = load_tokenizer(run, HOST)
    dataset = Assembly(run.load_config(HOST), HOST).component("data.dataset")
    assert torch.equal(load_file(cache["path"])["codes"].long(), encode_dataset(tokenizer, dataset, batch_size=4))


def test_a_generator_on_another_runs_tokenizer_and_exact_resume(trained, tmp_path):
    tokenizer_only = tmp_path / "tok"
    shutil.copytree(trained, tokenizer_only)
    out = tmp_path / "gen"
    assert main(train_args(out, flags=("--tokenizer", str(trained)))) == 0
    config = json.loads((out / "config.json").read_text())
    assert config["stages"] == ["generator"] and config["generator"]["tokenizer_run"] == str(trained.resolve())
    assert not (out / "eval.json").exists()  # no tokenizer was trained in this run
    uninterrupted = [r for r in lines(out) if "loss" in r]
    # Lose the last checkpoint, resume: steps 4-6 again, with the same losses.
    shutil.rmtree(out / "checkpoints" / "generator" / "step-00000006")
    assert main(["--no-progress", "train", "generator", "--resume", str(out)]) == 0
    assert [r for r in lines(out) if "loss" in r] == uninterrupted


def test_the_generator_contract(tmp_path):
    context = BuildContext(image_size=32, num_classes=4, cond_dim=16, codebook_size=16, code_grid=4)
    check_plugin(
        HOST,
        "generator",
        "vq_diffusion",
        {"depth": 1, "width": 16, "heads": 2, "num_steps": 10},
        context,
        tmp_dir=tmp_path,
    )


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
@pytest.mark.parametrize("codebook_size, grid", [(2, 1), (16384, 2), (16, 32)])
@pytest.mark.parametrize("loss", ["vb", "masked_ce"])
def test_training_and_sampling_stay_finite_at_the_extremes(codebook_size, grid, loss, precision):
    """K = 2 and K = 16384, a 1x1 and a 32x32 grid, batch 1, guidance 0 and 20, truncation near 0, in
    fp32 and under bf16 autocast (training's explicit attention and sampling's fused kernel): finite
    losses and gradients, codes in range."""
    context = BuildContext(image_size=32, cond_dim=8, codebook_size=codebook_size, code_grid=grid)
    generator = HOST.build(
        "generator",
        {"name": "vq_diffusion", "depth": 1, "width": 16, "heads": 2, "num_steps": 10, "loss": loss},
        context,
    )
    condition = ConditionTokens(torch.randn(1, 2, 8), torch.zeros(1, dtype=torch.bool))
    codes = torch.randint(codebook_size, (1, grid, grid))
    autocast = torch.autocast("cpu", dtype=torch.bfloat16, enabled=precision == "bf16")
    for t_draws in range(3):  # several t, t = 0 and t = T-1 among them with these seeds
        with autocast:
            loss_value, _ = generator.training_loss(codes, condition, generator=torch.Generator().manual_seed(t_draws))
        assert bool(torch.isfinite(loss_value)), loss_value
        generator.zero_grad()
        loss_value.backward()
        gradients = [p.grad for p in generator.parameters() if p.grad is not None]
        assert gradients and all(bool(torch.isfinite(g).all()) for g in gradients)
    generator.eval()
    sampler = HOST.build("sampler", "posterior")
    null = ConditionTokens(torch.randn(1, 2, 8), torch.ones(1, dtype=torch.bool))
    for guidance, truncation in ((0.0, 1.0), (20.0, 1e-6), (1.0, 0.5)):
        with autocast:
            sampled = generator.sample(
                condition,
                sampler,
                steps=3,
                null=null,
                guidance=guidance,
                truncation=truncation,
                generators=[torch.Generator().manual_seed(0)],
            )
        assert sampled.shape == (1, grid, grid) and int(sampled.max()) < codebook_size and int(sampled.min()) >= 0


def test_guidance_needs_the_null_condition():
    context = BuildContext(image_size=32, cond_dim=8, codebook_size=8, code_grid=2)
    generator = HOST.build(
        "generator", {"name": "vq_diffusion", "depth": 1, "width": 16, "heads": 2, "num_steps": 10}, context
    )
    condition = ConditionTokens(torch.randn(1, 2, 8), torch.zeros(1, dtype=torch.bool))
    with pytest.raises(ValueError, match="guidance != 1 needs the null condition"):
        generator.sample(condition, HOST.build("sampler", "posterior"), steps=2, guidance=3.0)


def test_a_generator_without_the_tokenizers_facts_is_refused():
    from vqtouch.core import ConfigError

    with pytest.raises(ConfigError, match="needs the tokenizer's codebook size and code grid"):
        HOST.build("generator", {"name": "vq_diffusion"}, BuildContext(image_size=32))


def test_label_to_touch_in_a_fresh_interpreter_never_imports_open_clip(trained, run_cli):
    """Model only what the scene requires: generating from a label run imports neither open_clip nor
    torchvision's models."""
    code = (
        "import sys; from vqtouch.plugins.generator import load_pipeline; "
        f"pipe = load_pipeline({str(trained)!r}); pipe(label=1, steps=2); "
        "print('open_clip' in sys.modules, 'torchvision.models' in sys.modules)"
    )
    import subprocess
    import sys

    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.split() == ["False", "False"]


def test_scores_stand_next_to_the_no_contact_background_and_the_contact_region(trained):
    result = json.loads((trained / "generation.json").read_text())
    for key in ("psnr", "background_psnr", "contact_psnr", "background_contact_psnr", "contact_mae"):
        assert isinstance(result[key], float), key
    assert 0 < result["contact_fraction"] < 1


def test_contact_region_scores_against_a_closed_form():
    from vqtouch.plugins.evaluation.contact import contact_region_scores

    background = torch.full((1, 3, 4, 4), 0.5)
    truth = background.clone()
    truth[..., :2, :] = 0.9  # the top half is in contact
    images = background.clone()
    images[..., :2, :] = 0.8  # off by 0.1 there, right elsewhere
    scores = contact_region_scores({"": images, "background_": background}, truth, background)
    assert scores["contact_fraction"] == 0.5
    assert scores["contact_mae"] == pytest.approx(0.1) and scores["background_contact_mae"] == pytest.approx(0.4)
    assert scores["contact_psnr"] == pytest.approx(20.0, abs=1e-3)  # MSE 0.01
    assert scores["background_contact_psnr"] == pytest.approx(10 * __import__("math").log10(1 / 0.16), abs=1e-3)


def test_evaluate_generation_rescores_a_run_reproducibly(trained, capsys):
    args = ["evaluate", "generation", "--run", str(trained), "--n", "3", "--steps", "3", "--sampler", "confidence"]
    assert main(args) == 0
    out = trained / "evaluation_generation_step-00000006_confidence_3.json"
    first = json.loads(out.read_text())
    assert first["samples"] == 3 and first["sampler"] == "confidence" and first["conditioner"] == "0:label"
    assert {"psnr", "background_psnr", "contact_psnr"} <= set(first)
    assert main(args) == 0 and json.loads(out.read_text()) == first
    capsys.readouterr()
    assert main([*args, "--conditioner", "1"]) == 2
    assert capsys.readouterr().err == (
        "vqtouch: error: --conditioner 1: this generator has conditioners 0..0 (label)\n"
    )


def touch_to_touch_args(
    out, trained, *extra, conditioner=("generator.conditioners.0.width=8", "generator.conditioners.0.depth=1")
):
    overrides = [o for o in TINY if not o.startswith("tokenizer.")] + [
        *conditioner,
        "generator.train.steps=1",
        "generator.num_samples=2",
        "generator.steps=1",
        *extra,
    ]
    args = [
        "--no-progress",
        "train",
        "generator",
        "--scene",
        "touch-to-touch",
        "--tokenizer",
        str(trained),
        "--out",
        str(out),
    ]
    for override in overrides:
        args += ["--set", override]
    return args


def test_a_condition_that_is_the_target_image_is_flagged(trained, tmp_path, capsys):
    """A tactile conditioner told to read the image it must produce could learn to copy it."""
    capsys.readouterr()
    assert main(touch_to_touch_args(tmp_path / "t2t", trained, "generator.conditioners.0.reads=tactile")) == 0
    assert (
        "vqtouch: warning: a conditioner reads samples' 'tactile' image, which is also the image the generator "
        "learns to produce"
    ) in capsys.readouterr().err


def test_touch_to_touch_conditions_on_the_paired_sensors_image(trained, tmp_path, capsys):
    """The scene generates DIGIT images from GelSight images of the same contacts: no warning, the
    conditioner reads 'tactile_source', and `generate --tactile IMG` feeds that conditioner."""
    from vqtouch.plugins.utils.images import save_png
    from vqtouch.plugins.generator import load_pipeline

    run = tmp_path / "t2t"
    capsys.readouterr()
    assert main(touch_to_touch_args(run, trained)) == 0
    assert "warning" not in capsys.readouterr().err
    config = json.loads((run / "config.json").read_text())
    assert config["sensor"]["name"] == "digit" and config["paired_sensor"]["name"] == "gelsight"
    # The sample grid: the GelSight conditions (top row), generated, ground truth (DIGIT); two columns.
    import numpy as np
    from PIL import Image

    from vqtouch.core import Assembly
    from vqtouch.plugins.runtime.run_dir import RunDir
    from vqtouch.plugins.utils.splits import split_dataset

    grid_HW3 = np.asarray(Image.open(run / "samples.png").convert("RGB"))
    assert grid_HW3.shape == (3 * (32 + 2) + 2, 2 * (32 + 2) + 2, 3)
    run_config = RunDir.open(run).load_config(HOST)
    dataset = Assembly(run_config, HOST).component("data.dataset")
    _, held_out = split_dataset(dataset, run_config.data.val_fraction, run_config.seed)
    for row, key in ((0, "tactile_source"), (2, "tactile")):
        expected = (held_out[1][key].permute(1, 2, 0).numpy() * 255).round()
        cell = grid_HW3[2 + row * 34 : 2 + row * 34 + 32, 36:68].astype(float)
        assert np.abs(cell - expected).max() <= 1, key
    pipe = load_pipeline(run, host=HOST)
    assert [c.sample_key for c in pipe.conditioners] == ["tactile_source"]
    image = tmp_path / "gelsight.png"
    save_png(torch.rand(3, 32, 32), image)
    assert (
        main(["generate", "--run", str(run), "--tactile", str(image), "--steps", "1", "--out", str(tmp_path / "gen")])
        == 0
    )
    assert json.loads((tmp_path / "gen" / "generate.json").read_text())["condition"] == "tactile"
    assert (tmp_path / "gen" / "sample_0000.png").is_file()


def test_the_baselines_stand_beside_every_score(trained):
    result = json.loads((trained / "generation.json").read_text())
    for prefix in ("ceiling_", "retrieval_", "class_mean_", "background_"):
        assert isinstance(result[prefix + "psnr"], float) and isinstance(result[prefix + "contact_psnr"], float), prefix
    assert (
        len({result[prefix + "psnr"] for prefix in ("", "ceiling_", "retrieval_", "class_mean_", "background_")}) == 5
    )


def test_retrieval_and_class_mean_against_hand_built_training_data():
    from vqtouch.core import Conditioner
    from vqtouch.plugins.generator.scoring import training_baselines

    class Onehot(Conditioner):
        sample_key = "label"

        def encode(self, condition):
            return torch.nn.functional.one_hot(torch.as_tensor(condition), 3).float().unsqueeze(1)

    conditioner = Onehot(cond_dim=3, num_tokens=1)
    train = [
        {"label": label, "tactile": torch.full((3, 2, 2), value)}
        for label, value in ((0, 0.1), (1, 0.5), (0, 0.3), (2, 0.9))
    ]
    batch = {"label": torch.tensor([0, 2])}
    baselines = training_baselines(conditioner, conditioner(batch["label"]), batch, train, torch.device("cpu"))
    assert baselines["retrieval_"][:, 0, 0, 0].tolist() == pytest.approx([0.1, 0.9])  # first image of each label
    assert baselines["class_mean_"][:, 0, 0, 0].tolist() == pytest.approx([0.2, 0.9])  # mean of 0.1 and 0.3


def test_tactile_codes_embeds_the_source_sensors_codes_and_keeps_its_tokenizer_out(trained, tmp_path, capsys):
    """The source image's codes under the source run's tokenizer (loaded independently here) decide
    the tokens; the frozen tokenizer gets no gradient and stays out of the checkpoint; the
    conditioner trains a touch-to-touch generator end to end."""
    from vqtouch.core import ConfigError
    from vqtouch.plugins.tokenizer import load_tokenizer

    context = BuildContext(image_size=32, cond_dim=16)
    conditioner = HOST.build("conditioner", {"name": "tactile_codes", "tokenizer": str(trained)}, context)
    reference, _ = load_tokenizer(trained, HOST)
    images = torch.rand(2, 3, 32, 32, generator=torch.Generator().manual_seed(0))
    codes_BN = reference.encode_codes(images).flatten(1)
    tokens = conditioner(images).tokens_BND
    assert conditioner.sample_key == "tactile_source" and tokens.shape == (2, conditioner.num_tokens, 16)
    assert conditioner.num_tokens == codes_BN.shape[1]
    # Each cell's token is its code's embedding (codes from the independently loaded tokenizer) plus
    # the cell's position: the tokens carry the source codes and nothing else of the image.
    assert torch.allclose(tokens - conditioner.position_ND, conditioner.code_embedding.weight[codes_BN], atol=1e-6)
    assert len(codes_BN.unique()) > 1
    tokens.sum().backward()
    assert conditioner.code_embedding.weight.grad is not None
    assert all(p.grad is None and not p.requires_grad for p in conditioner.source.autoencoder.parameters())
    assert not any(key.startswith(("frozen", "source", "autoencoder")) for key in conditioner.state_dict())
    with pytest.raises(ConfigError, match=r"^conditioner 'tactile_codes': tokenizer .*nowhere does not exist; train"):
        HOST.build("conditioner", {"name": "tactile_codes", "tokenizer": str(tmp_path / "nowhere")}, context)
    with pytest.raises(ConfigError, match=r"needs the source sensor's tokenizer: set generator.conditioners.N"):
        HOST.build("conditioner", {"name": "tactile_codes"}, context)

    run = tmp_path / "t2t_codes"
    source = json.dumps({"name": "tactile_codes", "tokenizer": str(trained)})
    assert main(touch_to_touch_args(run, trained, conditioner=[f"generator.conditioners.0={source}"])) == 0
    assert json.loads((run / "generation.json").read_text())["samples"] == 2


def test_a_mixed_generator_is_scored_with_each_of_its_conditioners(trained, tmp_path):
    """by_conditioner holds one score set per conditioner; the first is the run's own (not sampled twice)."""
    run = tmp_path / "mixed"
    overrides = [o for o in TINY if not o.startswith("tokenizer.")] + [
        'generator.conditioners=[{"name": "label"}, {"name": "text_scratch", "depth": 1, "width": 16, "heads": 2}]',
        "generator.train.steps=2",
        "generator.num_samples=2",
        "generator.steps=2",
    ]
    args = [
        "--no-progress",
        "train",
        "generator",
        "--scene",
        "label-to-touch",
        "--tokenizer",
        str(trained),
        "--out",
        str(run),
    ]
    for override in overrides:
        args += ["--set", override]
    assert main(args) == 0
    result = json.loads((run / "generation.json").read_text())
    assert list(result["by_conditioner"]) == ["0:label", "1:text_scratch"]
    first, second = result["by_conditioner"]["0:label"], result["by_conditioner"]["1:text_scratch"]
    assert all(result[key] == value for key, value in first.items())
    # After 2 training steps two conditions' samples can coincide (the canonical codes make the first
    # steps' predictions nearly condition-free); retrieval by each conditioner's own tokens cannot.
    assert second["samples"] == first["samples"] == 2
    assert second["retrieval_psnr"] != first["retrieval_psnr"]


def test_contact_weight_trains_on_the_contact_cells_of_a_grid_conditioner(trained, tmp_path, capsys):
    """The stage hands a generator with ``contact_weight`` each sample's contact cells: its log carries
    the contact loss and generation.json the share of contact cells; without the canonical
    background the config is refused in one line."""
    run = tmp_path / "contact"
    args = touch_to_touch_args(run, trained, "generator.model.contact_weight=1", "generator.train.steps=2")
    assert main(args) == 0
    note = json.loads((run / "generation.json").read_text())["canonical_background"]
    assert note["applied"] and 0 < note["contact_cells"] < 1
    logged = [r for r in lines(run) if "loss" in r]
    assert len(logged) == 2 and all(r["contact_bce"] > 0 for r in logged)
    capsys.readouterr()
    refused = touch_to_touch_args(
        tmp_path / "no", trained, "generator.model.contact_weight=1", "generator.train.canonical_background=false"
    )
    assert main(refused) == 2
    error = capsys.readouterr().err
    assert "generator.model.contact_weight needs generator.train.canonical_background=true" in error
    assert len(error.strip().splitlines()) == 1

"""Tokenizer autoencoders (every registered encoder), the tokenizer objective and its commands."""

import json

import pytest
import torch

from vqtouch.core import Autoencoder, BuildContext, ConfigError, load_plugins, resolve_config

HOST = load_plugins(autoload=False)
ENCODERS = HOST.registry("autoencoder").names()
TINY = {"channels": 16, "norm_groups": 8, "channel_multipliers": [1, 2], "z_channels": 16, "embed_dim": 8}
TINY_OPTIONS = {
    "vqgan": TINY,
    "dm_vqgan": TINY,
    "mae": {"patch_size": 8, "width": 32, "heads": 2, "decoder_width": 16, "depth": 1, "decoder_depth": 1},
}
CONTEXT = BuildContext(image_size=32)


def tiny_encoder(name, **options):
    torch.manual_seed(0)
    return HOST.build("autoencoder", {"name": name, **TINY_OPTIONS.get(name, {}), **options}, CONTEXT)


def test_both_paper_tokenizers_are_registered():
    assert {"vqgan", "dm_vqgan"} <= set(ENCODERS)


@pytest.mark.parametrize("name", ENCODERS)
def test_encoder_contract(name):
    encoder = tiny_encoder(name)
    assert isinstance(encoder, Autoencoder)
    images = torch.rand(2, 3, 32, 32) * 2 - 1
    latents = encoder.encode(images)
    grid = 32 // encoder.downsample_factor
    assert latents.shape == (2, encoder.latent_channels, grid, grid)
    assert encoder.decode(latents).shape == (2, 3, 32, 32)
    assert any(encoder.last_layer_weight() is p for p in encoder.parameters())


@pytest.mark.parametrize("name", ENCODERS)
@pytest.mark.parametrize("value", [-1.0, 1.0, 0.0])
def test_black_white_constant_images_and_batch_one_stay_finite(name, value):
    encoder = tiny_encoder(name)
    images = torch.full((1, 3, 32, 32), value)
    output = encoder.decode(encoder.encode(images))
    assert torch.isfinite(output).all()
    output.abs().mean().backward()
    assert all(torch.isfinite(p.grad).all() for p in encoder.parameters() if p.grad is not None)


@pytest.mark.parametrize("name", ENCODERS)
def test_bf16_autocast_is_finite_and_close_to_fp32(name):
    encoder = tiny_encoder(name).eval()
    images = torch.rand(2, 3, 32, 32) * 2 - 1
    with torch.no_grad():
        reference = encoder.decode(encoder.encode(images))
        encoder.reset_randomness()  # MAE: the same evaluation mask for both passes
        with torch.autocast("cpu", dtype=torch.bfloat16):
            low = encoder.decode(encoder.encode(images)).float()
    assert torch.isfinite(low).all()
    assert (low - reference).abs().mean() < 0.05 * reference.abs().mean() + 1e-3


def test_dm_vqgan_starts_close_to_vqgan_and_bounds_huge_offsets():
    dm = tiny_encoder("dm_vqgan")
    deformable = [m for m in dm.modules() if type(m).__name__ == "DeformableConv2d"]
    assert deformable, "dm_vqgan must contain deformable convolutions"
    fusion = [m for m in dm.modules() if type(m).__name__ == "MultiScaleFusion"]
    assert len(fusion) == 2 and all(torch.count_nonzero(f.fuse.weight) == 0 for f in fusion)
    for layer in deformable:  # push the offset branch to absurd raw offsets
        torch.nn.init.constant_(layer.offset_conv.bias, 1e6)
    output = dm.decode(dm.encode(torch.rand(1, 3, 32, 32) * 2 - 1))
    assert torch.isfinite(output).all()
    assert dm.offset_magnitude() is not None and dm.offset_magnitude() <= 4.0 + 1e-4


def test_dm_options_ablate_each_part():
    plain = tiny_encoder("dm_vqgan", deformable_levels=0, fusion=False)
    assert not any(type(m).__name__ in {"DeformableConv2d", "MultiScaleFusion"} for m in plain.modules())
    vanilla = tiny_encoder("vqgan")
    assert sum(p.numel() for p in plain.parameters()) == sum(p.numel() for p in vanilla.parameters())


def deformable_layers(image_size, **options):
    """Names of the DeformableConv2d modules of a narrow dm_vqgan (default channel_multipliers (1, 2, 2))."""
    torch.manual_seed(0)
    model = HOST.build(
        "autoencoder",
        {"name": "dm_vqgan", "channels": 8, "norm_groups": 8, "z_channels": 8, "embed_dim": 8, **options},
        BuildContext(image_size=image_size),
    )
    return [name for name, module in model.named_modules() if type(module).__name__ == "DeformableConv2d"]


def test_dm_vqgan_deformable_layers_do_not_depend_on_the_image_size():
    """The default must not thin out at larger images (it once counted 10 / 7 / 0 at 64 / 128 / 256 px)."""
    layers = {size: deformable_layers(size) for size in (32, 64, 128)}
    assert len(layers[64]) == 10 and layers[32] == layers[64] == layers[128]


def test_deformable_levels_count_from_the_latent_end():
    counts = [len(deformable_layers(32, deformable_levels=levels)) for levels in range(4)]
    # Lowest level: 1 encoder + 2 x 2 middle + 2 decoder blocks; each level above: 1 + 2 more.
    assert counts == [0, 7, 10, 13]
    # One level: the lowest one only (dec_levels runs from the latent end, so its index 0 is the lowest).
    assert deformable_layers(32, deformable_levels=1) == [
        "enc_levels.2.blocks.0.conv2",
        "enc_mid.0.conv2",
        "enc_mid.2.conv2",
        "dec_mid.0.conv2",
        "dec_mid.2.conv2",
        "dec_levels.0.blocks.0.conv2",
        "dec_levels.0.blocks.1.conv2",
    ]


def test_too_many_deformable_levels_is_an_error_not_a_clamp():
    with pytest.raises(
        ConfigError, match=r"deformable_levels = 4 exceeds the 3 feature level\(s\).*allowed 0 to 3"
    ) as error:
        deformable_layers(64, deformable_levels=4)
    assert "\n" not in str(error.value)
    with pytest.raises(ConfigError, match="allowed 0 to 2"):
        tiny_encoder("dm_vqgan", deformable_levels=3)  # TINY has 2 levels


@pytest.mark.parametrize("scale", [0.1, 1.0])
def test_dm_vqgan_offset_branches_train_at_their_own_learning_rate(scale):
    from vqtouch.plugins.tokenizer.training import TokenizerLossConfig
    from vqtouch.plugins.tokenizer.training import Tokenizer, TokenizerTask

    dm = tiny_encoder("dm_vqgan", offset_lr_scale=scale)
    [(got_scale, offsets)] = dm.learning_rate_scales()
    offset_ids = {id(p) for m in dm.modules() if hasattr(m, "offset_conv") for p in m.offset_conv.parameters()}
    assert got_scale == scale and {id(p) for p in offsets} == offset_ids and offset_ids
    assert tiny_encoder("vqgan").learning_rate_scales() == []
    quantizer = HOST.build("quantizer", {"name": "vq", "codebook_size": 8}, BuildContext(latent_dim=8))
    task = TokenizerTask(Tokenizer(dm, quantizer), TokenizerLossConfig(adversarial_weight=0))
    base, scaled = task.parameter_groups()["generator"]
    assert scaled["lr_scale"] == scale and {id(p) for p in scaled["params"]} == offset_ids
    everything = {id(p) for m in (dm, quantizer) for p in m.parameters()}
    assert {id(p) for p in base["params"]} == everything - offset_ids


def test_bad_configs_are_clear():
    with pytest.raises(ConfigError, match="multiple of norm_groups"):
        HOST.build("autoencoder", {"name": "vqgan", "channels": 20, "norm_groups": 8}, CONTEXT)
    with pytest.raises(ConfigError, match="not divisible by the tokenizer's downsampling factor"):
        HOST.build(
            "autoencoder",
            {"name": "vqgan", **TINY, "channel_multipliers": [1, 1, 1, 1, 1, 1]},
            BuildContext(image_size=48),
        )
    with pytest.raises(ConfigError, match="unknown option 'max_offset'"):
        HOST.build("autoencoder", {"name": "vqgan", "max_offset": 2.0}, CONTEXT)  # a DM option on vanilla VQGAN


def test_reconstruct_stage_never_builds_a_discriminator_dataset_or_generator(tmp_path, request):
    from vqtouch.core import Assembly
    from vqtouch.plugins.runtime.execution import run_stage
    from vqtouch.plugins.runtime.run_dir import RunDir

    config = resolve_config("reconstruction", overrides=[*TRAIN_OVERRIDES, 'stages=["tokenizer"]'], host=HOST)
    assert config.tokenizer.discriminator is not None  # the training stage uses it ...
    run = RunDir.create(config, host=HOST, path=tmp_path / "run")
    assert run_stage("tokenizer", Assembly(config, HOST), run).status == "ran"
    built_kinds = request.getfixturevalue("built_kinds")  # record from here on
    outcome = run_stage("reconstruct", Assembly(config, HOST), run)
    assert outcome.status == "ran", outcome.describe()
    # ... reconstructing loads the trained tokenizer and renders nothing: no discriminator, no data.
    assert sorted(set(built_kinds)) == ["autoencoder", "metric", "quantizer", "sensor_family"]


def test_reconstruct_stage_says_why_when_the_sensor_has_no_real_frames(tmp_path):
    from vqtouch.core import Assembly
    from vqtouch.plugins.runtime.execution import run_stage
    from vqtouch.plugins.runtime.run_dir import RunDir

    config = resolve_config(
        "reconstruction", overrides=[*TRAIN_OVERRIDES, 'stages=["tokenizer"]', "sensor=digit"], host=HOST
    )
    run = RunDir.create(config, host=HOST, path=tmp_path / "run")
    before = run_stage("reconstruct", Assembly(config, HOST), run)
    assert before.describe().startswith("cannot run: no trained tokenizer in this run")
    assert run_stage("tokenizer", Assembly(config, HOST), run).status == "ran"
    after = run_stage("reconstruct", Assembly(config, HOST), run)
    assert after.describe() == (
        "cannot run: sensor family 'digit' declares no real reference frames "
        "(SensorFamily.reference_frames) to reconstruct"
    )


# -- the objective ----------------------------------------------------------------------------


def test_adaptive_weight_is_guarded_against_non_finite_values():
    from vqtouch.plugins.tokenizer.discriminator import adaptive_weight

    layer = torch.nn.Parameter(torch.ones(3))
    good = adaptive_weight((layer * 2).sum(), (layer * 4).sum(), layer)
    assert good == pytest.approx(0.5, rel=1e-3)  # ||grad nll|| / ||grad g|| = 2 / 4
    nan = adaptive_weight((layer * float("nan")).sum(), (layer * 4).sum(), layer)
    assert nan == 0.0
    huge = adaptive_weight((layer * 1e12).sum(), (layer * 1e-12).sum(), layer, maximum=10.0)
    assert huge == 10.0


def test_hinge_loss_closed_form():
    from vqtouch.plugins.tokenizer.discriminator import hinge_discriminator_loss

    real, fake = torch.tensor([2.0, 0.5]), torch.tensor([-2.0, 0.0])
    # relu(1 - real) = [0, 0.5] -> 0.25; relu(1 + fake) = [0, 1] -> 0.5; half their sum = 0.375
    assert float(hinge_discriminator_loss(real, fake)) == pytest.approx(0.375)


TRAIN_OVERRIDES = [
    "tokenizer.autoencoder.channels=16",
    "tokenizer.autoencoder.norm_groups=8",
    "tokenizer.autoencoder.channel_multipliers=[1,2]",
    "tokenizer.autoencoder.z_channels=16",
    "tokenizer.autoencoder.embed_dim=8",
    "tokenizer.quantizer.codebook_size=32",
    "data.image_size=32",
    "data.batch_size=4",
    "data.dataset.num_samples=24",
    "tokenizer.train.steps=4",
    "tokenizer.train.log_every=1",
    "tokenizer.train.checkpoint_every=2",
    "tokenizer.loss.perceptual=none",
    'tokenizer.discriminator={"name": "patchgan"}',
    "tokenizer.loss.disc_start=2",
    'metrics=[{"name": "psnr"}, {"name": "ssim"}]',
]


# -- MAE baseline -------------------------------------------------------------------------------


@pytest.mark.parametrize("ratio", [0.25, 0.5, 0.75])
def test_mae_hides_the_configured_fraction_and_pastes_visible_patches(ratio):
    mae = tiny_encoder("mae", mask_ratio=ratio).eval()
    images = torch.rand(3, 3, 32, 32) * 2 - 1
    with torch.no_grad():
        latents = mae.encode(images)
        reconstruction = mae.decode(latents)
    visible = mae.visible_mask(latents)
    assert visible.float().mean().item() == pytest.approx(1 - ratio, abs=1 / 16)
    assert torch.equal(mae.patchify(reconstruction)[visible], mae.patchify(images)[visible])
    assert not torch.equal(mae.patchify(reconstruction)[~visible], mae.patchify(images)[~visible])


@pytest.mark.parametrize("paste_visible", [True, False])
def test_mae_decode_depends_only_on_its_latents(paste_visible):
    """decode(latents) must not read what the last encode saw (it once pasted that call's pixels)."""
    mae = tiny_encoder("mae", paste_visible=paste_visible).eval()
    first, second = torch.rand(2, 2, 3, 32, 32) * 2 - 1
    with torch.no_grad():
        latents = mae.encode(first)
        right_after = mae.decode(latents)
        mae.encode(second)  # same batch size: another call's images and mask in between
        later = mae.decode(latents)
    assert torch.equal(later, right_after)
    assert latents.shape[1] == mae.latent_channels == 16 + 1 + (3 * 8 * 8 if paste_visible else 0)


def test_mae_patchify_round_trip_and_repeatable_eval_masks():
    mae = tiny_encoder("mae")
    images = torch.rand(2, 3, 32, 32)
    assert torch.equal(mae.unpatchify(mae.patchify(images)), images)
    first, second = tiny_encoder("mae").eval(), tiny_encoder("mae").eval()
    assert torch.equal(first.visible_mask(first.encode(images)), second.visible_mask(second.encode(images)))


def test_identity_quantizer_passes_latents_through():
    quantizer = HOST.build("quantizer", "identity", BuildContext(latent_dim=4))
    latents = torch.randn(2, 4, 3, 3, dtype=torch.bfloat16)
    output = quantizer(latents)
    assert torch.equal(output.quantized_BDhw, latents.float()) and float(output.loss) == 0.0
    assert float(output.perplexity) == 1.0
    with pytest.raises(ValueError, match="no codebook"):
        quantizer.lookup(output.codes_Bhw)


@pytest.mark.parametrize("encoder", ["vqgan", "dm_vqgan"])
def test_train_tokenizer_end_to_end_then_reconstruct_and_evaluate(tmp_path, capsys, encoder):
    from vqtouch.plugins.cli.app import main

    run = tmp_path / "run"
    args = ["--no-progress", "train", "tokenizer", "--out", str(run), "--set", f"tokenizer.autoencoder.name={encoder}"]
    for override in TRAIN_OVERRIDES:
        args += ["--set", override]
    assert main(args) == 0
    result = json.loads((run / "eval.json").read_text())
    assert result["step"] == 4 and result["val_samples"] == 2 and 0 <= result["ssim"] <= 1
    assert 0 < result["codebook_usage"] <= 1 and result["perplexity"] >= 1
    lines = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    lines = [line for line in lines if "val_loss" not in line]  # the training lines (checkpoints add scores)
    assert "d_loss" not in lines[1] and "d_loss" in lines[2]  # the discriminator starts at disc_start=2
    assert {p.name for p in (run / "checkpoints" / "step-00000004").iterdir()} == {
        "autoencoder.safetensors",
        "quantizer.safetensors",
        "discriminator.safetensors",
        "trainer_state.safetensors",
    }
    capsys.readouterr()
    assert main(["reconstruct", "--run", str(run), "--real-frames", "gelsight", "--out", str(tmp_path / "rec")]) == 0
    assert "48 images from real gelsight frames" in capsys.readouterr().out
    assert json.loads((tmp_path / "rec" / "reconstruct.json").read_text())["images"] == 48
    assert main(["evaluate", "reconstruction", "--run", str(run)]) == 0
    evaluation = json.loads(capsys.readouterr().out)
    assert evaluation["ssim"] == pytest.approx(result["ssim"], abs=1e-6)  # same weights, same split


def test_mae_trains_through_the_tokenizer_pipeline(tmp_path):
    from vqtouch.plugins.cli.app import main

    run = tmp_path / "run"
    args = ["--no-progress", "train", "tokenizer", "--out", str(run)]
    for override in TRAIN_OVERRIDES:
        if not override.startswith(("tokenizer.autoencoder", "tokenizer.quantizer")):
            args += ["--set", override]
    args += [
        "--set",
        'tokenizer.autoencoder={"name": "mae", "patch_size": 8, "width": 32, "heads": 2, '
        '"decoder_width": 16, "depth": 1, "decoder_depth": 1, "mask_ratio": 0.75}',
        "--set",
        "tokenizer.quantizer=identity",
        "--set",
        "tokenizer.discriminator=null",
    ]
    assert main(args) == 0
    result = json.loads((run / "eval.json").read_text())
    # Continuous latents: no codebook, so no codebook usage is reported (not a fake "1 code used").
    assert result["step"] == 4 and 0 <= result["ssim"] <= 1 and "codes_used" not in result


def test_train_tokenizer_resume_continues_the_run(tmp_path, capsys):
    from vqtouch.plugins.cli.app import main

    run = tmp_path / "run"
    base = ["--no-progress", "train", "tokenizer", "--set", "tokenizer.autoencoder.name=vqgan"]
    for override in TRAIN_OVERRIDES:
        base += ["--set", override]
    assert main(base + ["--out", str(run)]) == 0
    config = json.loads((run / "config.json").read_text())
    config["tokenizer"]["train"]["steps"] = 6
    (run / "config.json").write_text(json.dumps(config))
    assert main(["--no-progress", "train", "tokenizer", "--resume", str(run)]) == 0
    assert "resumed" in capsys.readouterr().out
    assert json.loads((run / "eval.json").read_text())["step"] == 6
    assert main(["train", "tokenizer", "--resume", str(run), "--set", "seed=2"]) == 2


@pytest.mark.parametrize("codebook_size", [2, 16384])
def test_tiny_and_huge_codebooks_train_without_nan(tmp_path, codebook_size):
    from vqtouch.plugins.cli.app import main

    run = tmp_path / "run"
    args = [
        "--no-progress",
        "train",
        "tokenizer",
        "--out",
        str(run),
        "--set",
        "tokenizer.autoencoder.name=vqgan",
        "--set",
        "tokenizer.train.precision=bf16",
    ]
    for override in TRAIN_OVERRIDES:
        args += ["--set", override]
    args += ["--set", f"tokenizer.quantizer.codebook_size={codebook_size}"]
    assert main(args) == 0
    lines = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    lines = [line for line in lines if "val_loss" not in line]  # the training lines (checkpoints add scores)
    assert all(
        all(value == value and abs(value) != float("inf") for value in line.values() if isinstance(value, float))
        for line in lines
    )
    assert lines[-1]["skipped_steps"] == 0.0


def test_evaluation_reports_the_codes_the_held_out_images_use(host):
    """Codebook usage in the evaluation is the quantizer's own count over exactly the evaluated
    images: checked against the distinct codes of an independent pass over the same images."""
    from vqtouch.plugins.tokenizer.training import Tokenizer, evaluate_reconstruction

    sensor = host.build("sensor_family", "gelsight")
    dataset = host.build("dataset", {"name": "procedural", "num_samples": 10, "image_size": 32}, CONTEXT, sensor=sensor)
    autoencoder = tiny_encoder("vqgan")
    quantizer = host.build(
        "quantizer",
        {"name": "vq", "codebook_size": 64},
        CONTEXT.model_copy(update={"latent_dim": autoencoder.latent_channels}),
    )
    tokenizer = Tokenizer(autoencoder, quantizer)
    tokenizer.quantizer(torch.randn(4, autoencoder.latent_channels, 8, 8))  # usage from before must not count
    scores = evaluate_reconstruction(tokenizer, dataset, {}, batch_size=4)
    images = torch.stack([dataset[i]["tactile"] for i in range(len(dataset))])
    with torch.no_grad():
        codes = tokenizer.reconstruct(images)[1].codes_Bhw
    counts = torch.bincount(codes.flatten(), minlength=64).double()
    probabilities = counts[counts > 0] / counts.sum()
    assert scores["codes_used"] == int((counts > 0).sum())
    assert scores["codebook_usage"] == pytest.approx(scores["codes_used"] / 64)
    assert scores["perplexity"] == pytest.approx(
        float(torch.exp(-(probabilities * probabilities.log()).sum())), rel=1e-9
    )


# -- precision of the building blocks -----------------------------------------------------------


def test_groupnorm_is_torch_s_in_float32_and_float32_under_bf16_autocast():
    from vqtouch.plugins.tokenizer.blocks import group_norm

    torch.manual_seed(0)
    norm = group_norm(16, 4)
    with torch.no_grad():
        norm.weight.normal_()
        norm.bias.normal_()
    x = torch.randn(2, 16, 5, 5)
    reference = torch.nn.GroupNorm(4, 16, eps=1e-6)
    reference.load_state_dict(norm.state_dict())
    assert torch.equal(norm(x), reference(x))
    with torch.autocast("cpu", dtype=torch.bfloat16):
        low = norm(x.bfloat16())
    assert low.dtype == torch.float32
    torch.testing.assert_close(low, reference(x.bfloat16().float()), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("name", ["vqgan", "dm_vqgan"])
def test_under_bf16_autocast_the_residual_stream_stays_float32(name):
    """Every block's output (the stream) is float32 under bf16 autocast, the convolutions bf16."""
    from vqtouch.plugins.tokenizer.blocks import AttentionBlock, MultiScaleFusion, ResnetBlock

    encoder = tiny_encoder(name)
    outputs = []
    hooks = [
        module.register_forward_hook(lambda module, args, output: outputs.append((type(module).__name__, output.dtype)))
        for module in encoder.modules()
        if isinstance(module, (ResnetBlock, AttentionBlock, MultiScaleFusion))
    ]
    images = torch.rand(2, 3, 32, 32) * 2 - 1
    with torch.autocast("cpu", dtype=torch.bfloat16):
        reconstruction = encoder.decode(encoder.encode(images))
    for hook in hooks:
        hook.remove()
    assert outputs and {dtype for _, dtype in outputs} == {torch.float32}, outputs
    assert torch.isfinite(reconstruction.float()).all()

"""How the condition reaches the generator: the aligned condition grid and the global
path, old checkpoints without them, canonical-background codes, the mean masked loss and the
learning-rate schedule."""

import math

import pytest
import torch
import torch.nn.functional as F

from vqtouch.conditioners.image_cnn import ImageCnnConditioner, grid_stage_for
from vqtouch.core import BuildContext, load_missing_as_zeros, load_plugins
from vqtouch.core.checkpoint import load_state_strict
from vqtouch.plugins.training.settings import TrainConfig, learning_rate_factor
from vqtouch.plugins.generator.codes import canonical_background
from vqtouch.plugins.generator.denoiser import DiffusionTransformer
from vqtouch.plugins.generator.diffusion import MaskReplaceSchedule, masked_ce_loss

HOST = load_plugins(autoload=False)
CONTEXT = BuildContext(image_size=32, num_classes=3, codebook_size=16, code_grid=8, cond_dim=24)


def network(seed=0, **extra):
    torch.manual_seed(seed)
    return DiffusionTransformer(16, 10, (8, 8), 24, depth=2, width=32, heads=4, **extra).eval()


def randomise_condition_paths(net):
    with torch.no_grad():
        for layer in (net.cond_global, net.grid_proj):
            layer.weight.normal_(0, 0.5)
            layer.bias.normal_(0, 0.5)


def test_the_condition_grid_changes_the_logits_at_its_own_place():
    net = network()
    randomise_condition_paths(net)
    codes = torch.full((1, 64), 16)
    tokens = torch.randn(1, 2, 24)
    grid = torch.randn(1, 24, 8, 8)
    base = net(codes, torch.tensor([5]), condition=tokens, condition_grid=grid)
    changed_grid = grid.clone()
    changed_grid[:, :, 2, 3] += 3.0
    changed = net(codes, torch.tensor([5]), condition=tokens, condition_grid=changed_grid)
    difference_L = (changed - base).abs().sum(1)[0]
    # Self-attention spreads the change, but the token at the changed cell moves most.
    assert int(difference_L.argmax()) == 2 * 8 + 3
    assert not torch.allclose(net(codes, torch.tensor([5]), condition=tokens), base)


def test_a_grid_of_another_size_is_resized_to_the_code_grid():
    net = network()
    randomise_condition_paths(net)
    fine = torch.randn(1, 24, 32, 32)
    coarse = F.interpolate(fine, size=(8, 8), mode="area")
    tokens = torch.randn(1, 2, 24)
    codes, t = torch.full((1, 64), 16), torch.tensor([3])
    torch.testing.assert_close(
        net(codes, t, condition=tokens, condition_grid=fine), net(codes, t, condition=tokens, condition_grid=coarse)
    )
    with pytest.raises(ValueError, match="condition grid"):
        net(codes, t, condition=tokens, condition_grid=torch.randn(1, 5, 8, 8))


def test_new_paths_start_as_no_ops_and_old_checkpoints_load_as_before():
    net = network()
    codes, t, tokens = torch.randint(0, 17, (2, 64)), torch.tensor([1, 7]), torch.randn(2, 3, 24)
    grid = torch.randn(2, 24, 8, 8)
    # Zero-initialised: a fresh network's grid and global paths add nothing.
    torch.testing.assert_close(net(codes, t, condition=tokens, condition_grid=grid), net(codes, t, condition=tokens))
    randomise_condition_paths(net)
    old_state = {k: v for k, v in net.state_dict().items() if not k.startswith(("cond_global", "grid_proj"))}
    reloaded = network(seed=1)
    randomise_condition_paths(reloaded)
    load_state_strict(reloaded, old_state, "old.safetensors")
    assert reloaded.grid_proj.weight.abs().sum() == 0 and reloaded.cond_global.bias.abs().sum() == 0
    plain = network(seed=2)
    plain.load_state_dict(old_state)  # torch's own loader honours the same declaration
    torch.testing.assert_close(plain(codes, t, condition=tokens), reloaded(codes, t, condition=tokens))


def test_load_missing_as_zeros_fills_only_what_was_declared():
    class Two(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.kept, self.added = torch.nn.Linear(2, 2), torch.nn.Linear(2, 2)
            load_missing_as_zeros(self, "added")

    module = Two()
    state = {k: v for k, v in module.state_dict().items() if k.startswith("kept")}
    load_state_strict(module, state, "f")
    assert module.added.weight.abs().sum() == 0
    with pytest.raises(Exception, match="missing 1 tensor"):
        load_state_strict(Two(), {"kept.weight": torch.zeros(2, 2)}, "f")


def test_image_conditioners_hand_an_aligned_grid_and_zero_for_null_rows():
    conditioner = HOST.build("conditioner", {"name": "tactile", "reads": "tactile"}, CONTEXT)
    assert conditioner.grid_stage == grid_stage_for(32, 8, 3) == 1
    images = torch.rand(3, 3, 32, 32)
    tokens = conditioner(images, torch.tensor([False, True, False]))
    assert tokens.grid_BDhw.shape == (3, 24, 8, 8)
    assert tokens.grid_BDhw[1].abs().sum() == 0 and tokens.grid_BDhw[0].abs().sum() > 0
    # A shifted contact shifts the grid with it (the map is computed, not learned per position).
    wide = HOST.build(
        "conditioner",
        {"name": "tactile", "reads": "tactile"},
        CONTEXT.model_copy(update={"image_size": 64, "code_grid": 16}),
    )
    blob = torch.zeros(1, 3, 64, 64)
    blob[..., 16:24, 16:24] = 1.0
    grid_a = wide.encode_with_grid(blob)[1]
    grid_b = wide.encode_with_grid(torch.roll(blob, shifts=(16, 16), dims=(-2, -1)))[1]
    torch.testing.assert_close(
        torch.roll(grid_a, shifts=(4, 4), dims=(-2, -1))[..., 6:12, 6:12], grid_b[..., 6:12, 6:12], atol=1e-5, rtol=1e-5
    )
    assert not torch.allclose(grid_a[..., 6:12, 6:12], grid_b[..., 6:12, 6:12], atol=1e-3)
    without = HOST.build("conditioner", {"name": "tactile", "reads": "tactile", "spatial": False}, CONTEXT)
    assert without(images).grid_BDhw is None
    assert HOST.build("conditioner", {"name": "label"}, CONTEXT)(torch.tensor([0, 2])).grid_BDhw is None


@pytest.mark.parametrize(
    "image, grid, depth, stage",
    [(64, 16, 3, 1), (64, 8, 3, 2), (64, 32, 3, 0), (64, 4, 3, 2), (256, 16, 6, 3), (64, 0, 3, None)],
)
def test_grid_stage_is_the_smallest_trunk_map_covering_the_code_grid(image, grid, depth, stage):
    assert grid_stage_for(image, grid, depth) == stage
    if stage is not None:
        conditioner = ImageCnnConditioner("tactile", 8, 8, depth, 2, grid_stage=stage)
        side = conditioner.encode_with_grid(torch.rand(1, 3, image, image))[1].shape[-1]
        assert side == image // 2 ** (stage + 1) and (side >= grid or stage == depth - 1)


def test_a_generator_trained_with_a_grid_samples_with_guidance_and_batch_one():
    generator = HOST.build("generator", {"name": "vq_diffusion", "depth": 1, "width": 32, "num_steps": 10}, CONTEXT)
    conditioner = HOST.build("conditioner", {"name": "tactile", "reads": "tactile"}, CONTEXT)
    sampler = HOST.build("sampler", {"name": "posterior"})
    randomise_condition_paths(generator.network)
    for batch in (1, 2):
        condition = conditioner(torch.rand(batch, 3, 32, 32))
        for guidance in (1.0, 50.0):
            codes = generator.sample(condition, sampler, steps=3, null=conditioner.null(batch), guidance=guidance)
            assert codes.shape == (batch, 8, 8) and int(codes.min()) >= 0 and int(codes.max()) < 16


class _PatchTokenizer:
    """Codes = one per 4x4 patch: 0 for the background's patch, 1 + patch mean quantised otherwise
    (a stand-in whose encoder is local, so canonical cells are known in closed form)."""

    device = torch.device("cpu")

    def encode_codes(self, images):
        means = F.avg_pool2d(images.mean(1, keepdim=True), 4)[:, 0]
        return torch.where(means < 0.05, torch.zeros_like(means), 1 + (means * 10).round().clamp(max=14)).long()

    def decode_codes(self, codes):
        values = torch.where(codes == 0, torch.zeros_like(codes).float(), (codes.float() - 1) / 10)
        return F.interpolate(values[:, None].expand(-1, 3, -1, -1), scale_factor=4, mode="nearest")

    def reconstruct(self, images):
        return self.decode_codes(self.encode_codes(images)), None


def test_canonical_background_replaces_exactly_the_cells_away_from_the_contact():
    tokenizer = _PatchTokenizer()
    background = torch.zeros(3, 32, 32)
    images = torch.zeros(2, 3, 32, 32)
    images[0, :, 8:12, 8:12] = 0.9  # one contact cell at (2, 2)
    codes = tokenizer.encode_codes(images)
    synonyms = codes.clone()
    synonyms[codes == 0] = 15  # the encoder's synonym for "no contact", decoding to the same image
    canonical, changed = canonical_background(synonyms, _SynonymTokenizer(tokenizer), background, margin=1)
    near = torch.zeros(8, 8, dtype=torch.bool)
    near[1:4, 1:4] = True
    assert torch.equal(canonical[0][near], synonyms[0][near])
    assert (canonical[0][~near] == 0).all() and (canonical[1] == 0).all()
    assert changed == pytest.approx((64 - 9 + 64) / 128)
    kept_all, _ = canonical_background(synonyms, _SynonymTokenizer(tokenizer), background, margin=8)
    assert torch.equal(kept_all[0], synonyms[0])


class _ShiftedDecoderTokenizer(_PatchTokenizer):
    """The patch tokenizer with a decoder adapted to a brighter sensor: it draws every code 0.3 brighter
    (a global shift, which the contact mask's noise estimate absorbs, hiding the contact)."""

    def decode_codes(self, codes):
        return super().decode_codes(codes) + 0.3 * (codes != 99).float()[:, None].repeat_interleave(
            4, 2
        ).repeat_interleave(4, 3)


def test_canonical_background_finds_the_contact_on_the_images_when_given_them():
    tokenizer = _ShiftedDecoderTokenizer()
    background = torch.zeros(3, 32, 32)
    images = torch.zeros(1, 3, 32, 32)
    images[0, :, 8:12, 8:12] = 0.6  # decoded at 0.9 over a 0.3 shift: below the noise-scaled threshold
    codes = tokenizer.encode_codes(images)
    near = torch.zeros(8, 8, dtype=torch.bool)
    near[1:4, 1:4] = True
    from_images, changed = canonical_background(codes, tokenizer, background, margin=1, images_N3HW=images)
    assert torch.equal(from_images[0][near], codes[0][near]) and (from_images[0][~near] == 0).all()
    # From the decoding, the shifted appearance hides the contact: its cell is lost to the background.
    from_decoding, _ = canonical_background(codes, tokenizer, background, margin=1)
    assert from_decoding[0, 2, 2] == 0 != codes[0, 2, 2]


class _SynonymTokenizer:
    """The patch tokenizer whose code 15 is a synonym of the background's code 0."""

    device = torch.device("cpu")

    def __init__(self, inner):
        self.inner = inner

    def encode_codes(self, images):
        return self.inner.encode_codes(images)

    def decode_codes(self, codes):
        return self.inner.decode_codes(torch.where(codes == 15, torch.zeros_like(codes), codes))


def test_the_mean_masked_loss_is_the_mean_cross_entropy_of_masked_tokens():
    schedule = MaskReplaceSchedule(8, 10)
    torch.manual_seed(0)
    logits = torch.randn(2, 8, 6)
    x0 = torch.randint(0, 8, (2, 6))
    xt = x0.clone()
    xt[0, [1, 4]] = 8
    xt[1, 0] = 8
    loss = masked_ce_loss(logits, x0, xt, torch.tensor([3, 9]), schedule, weighting="mean")
    nll = -F.log_softmax(logits, 1).gather(1, x0[:, None])[:, 0]
    torch.testing.assert_close(loss, torch.stack([nll[0, [1, 4]].mean(), nll[1, 0]]))
    unmasked = masked_ce_loss(logits, x0, x0, torch.tensor([3, 9]), schedule, weighting="mean")
    assert torch.equal(unmasked, torch.zeros(2))
    with pytest.raises(ValueError, match="weighting"):
        masked_ce_loss(logits, x0, xt, torch.tensor([3, 9]), schedule, weighting="flat")


def test_learning_rate_schedule_warms_up_then_follows_a_half_cosine():
    config = TrainConfig(steps=110, warmup_steps=10, lr_schedule="cosine", min_lr_ratio=0.2)
    assert [learning_rate_factor(config, s) for s in (0, 4, 9)] == [0.1, 0.5, 1.0]
    assert learning_rate_factor(config, 10) == 1.0
    assert learning_rate_factor(config, 109) == pytest.approx(0.2)
    assert learning_rate_factor(config, 59.5) == pytest.approx(0.2 + 0.8 * 0.5 * (1 + math.cos(math.pi * 0.5)))
    assert learning_rate_factor(TrainConfig(steps=50), 30) == 1.0


@pytest.fixture(scope="module")
def touch_run(tmp_path_factory):
    """A tiny trained touch-to-touch run (32 px, tactile conditioner)."""
    from generator_runs import train_args  # registered by conftest

    from vqtouch.plugins.cli.app import main

    out = tmp_path_factory.mktemp("t2t") / "run"
    assert main(train_args(out, "generator.conditioners.0.width=8", scene="touch-to-touch")) == 0
    return out


def test_a_trained_touch_to_touch_run_keeps_its_grid_and_trains_on_canonical_codes(touch_run):
    import json

    from vqtouch.plugins.generator import load_pipeline

    result = json.loads((touch_run / "generation.json").read_text())
    assert result["canonical_background"]["applied"] is True
    assert 0 <= result["canonical_background"]["cells_changed"] <= 1
    pipe = load_pipeline(touch_run, host=HOST)
    conditioner = pipe.conditioners[0]
    assert conditioner.grid_stage == grid_stage_for(32, pipe.generator.grid_hw[0], 3)
    condition = conditioner(torch.rand(2, 3, 32, 32))
    assert condition.grid_BDhw is not None and condition.grid_BDhw.shape[-1] >= pipe.generator.grid_hw[1]


def test_keeping_revealed_tokens_warns_only_with_real_replacement_noise():
    import warnings

    from vqtouch.plugins.generator.samplers import KeepUnmaskedWarning, PosteriorSampler

    def denoise(codes_BL, t_B):
        return torch.log_softmax(torch.zeros(len(codes_BL), 9, codes_BL.shape[1]), 1)

    generators = [torch.Generator().manual_seed(0)]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        PosteriorSampler().sample(denoise, MaskReplaceSchedule(8, 10), length=4, steps=3, generators=generators)
        PosteriorSampler(keep_unmasked=False).sample(
            denoise, MaskReplaceSchedule(8, 10, att_T=0.0, ctt_T=0.9), length=4, steps=3, generators=generators
        )
    with pytest.warns(KeepUnmaskedWarning, match="keep_unmasked=false"):
        PosteriorSampler().sample(
            denoise, MaskReplaceSchedule(8, 10, att_T=0.0, ctt_T=0.9), length=4, steps=3, generators=generators
        )


def test_contact_centroid_error_is_the_distance_between_contact_centres():
    from vqtouch.plugins.evaluation.directions import lower_is_better
    from vqtouch.plugins.evaluation.contact import contact_centroid_errors, contact_centroids

    background = torch.full((1, 3, 32, 32), 0.5)
    truth = background.repeat(2, 1, 1, 1)
    truth[0, :, 4:8, 10:14] = 0.9  # centre (5.5, 11.5)
    truth[1, :, 20:22, 16:26] = 0.1  # centre (20.5, 20.5)
    torch.testing.assert_close(contact_centroids(truth, background), torch.tensor([[5.5, 11.5], [20.5, 20.5]]))
    moved = torch.roll(truth, shifts=(3, 4), dims=(-2, -1))
    errors = contact_centroid_errors({"": moved, "background_": background.expand_as(truth)}, truth, background)
    assert errors["contact_centroid_error_px"] == pytest.approx(5.0)
    # Drawing nothing is scored as guessing the image centre (15.5, 15.5).
    expected = (math.hypot(10, 4) + math.hypot(5, 5)) / 2
    assert errors["background_contact_centroid_error_px"] == pytest.approx(expected)
    assert lower_is_better("contact_centroid_error_px")


def test_evaluate_generation_scores_a_bundle_into_out(touch_run, tmp_path, monkeypatch, capsys):
    import json

    from vqtouch.plugins.cli.app import main
    from vqtouch.plugins.pretrained import bundle as bundle_module

    bundles = tmp_path / "bundles"
    bundle_module.export_bundle(touch_run, "tiny", HOST, root=bundles)
    monkeypatch.setattr(bundle_module, "BUNDLES", bundles)
    out = tmp_path / "scores"
    assert (
        main(
            [
                "--no-progress",
                "evaluate",
                "generation",
                "--run",
                "pretrained:tiny",
                "--n",
                "3",
                "--steps",
                "2",
                "--metrics",
                "psnr",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    result = json.loads((out / "generation.json").read_text())
    assert result["checkpoint"] == "pretrained:tiny"
    ((name, scores),) = result["by_conditioner"].items()
    assert name == "0:tactile" and scores["samples"] == 3 and scores["steps"] == 2
    for key in (
        "contact_psnr",
        "retrieval_contact_psnr",
        "ceiling_contact_psnr",
        "background_contact_psnr",
        "contact_centroid_error_px",
        "retrieval_contact_centroid_error_px",
    ):
        assert math.isfinite(scores[key]), key
    assert (out / "samples_0_tactile.png").is_file()
    # The same scores as scoring the run itself (the bundle holds its weights in fp16: close, not equal).
    assert (
        main(
            [
                "--no-progress",
                "evaluate",
                "generation",
                "--run",
                str(touch_run),
                "--n",
                "3",
                "--steps",
                "2",
                "--metrics",
                "psnr",
                "--out",
                str(tmp_path / "run_scores"),
            ]
        )
        == 0
    )
    direct = json.loads((tmp_path / "run_scores" / "generation.json").read_text())["by_conditioner"]["0:tactile"]
    assert direct["ceiling_contact_psnr"] == pytest.approx(scores["ceiling_contact_psnr"], abs=0.5)
    capsys.readouterr()
    assert main(["evaluate", "generation", "--run", "pretrained:tiny", "--n", "2"]) == 2
    assert "read-only; give --out" in capsys.readouterr().err
    assert main(["evaluate", "generation", "--run", "pretrained:nope", "--out", str(tmp_path / "x")]) == 2
    assert "no bundled checkpoints named 'nope'" in capsys.readouterr().err


def test_the_classifier_can_learn_from_the_tokenizers_reconstructions(monkeypatch):
    from vqtouch.plugins.evaluation import distribution
    from vqtouch.plugins.generator.scoring import HeldOutConditions, distribution_scorer

    seen = {}

    class Recording:
        def __init__(self, real, labels, train_images, train_labels, **options):
            seen["train"] = torch.stack(list(train_images))

    monkeypatch.setattr(distribution, "DistributionScorer", Recording)
    torch.manual_seed(0)
    pool = [{"tactile": torch.rand(3, 32, 32), "label": i % 2} for i in range(4)]
    conditions = HeldOutConditions([{}], [0], torch.rand(1, 3, 32, 32), [0])
    distribution_scorer(conditions, pool, [], 0)
    torch.testing.assert_close(seen["train"], torch.stack([s["tactile"] for s in pool]))
    tokenizer = _PatchTokenizer()
    distribution_scorer(conditions, pool, [], 0, tokenizer=tokenizer)
    expected = tokenizer.decode_codes(tokenizer.encode_codes(torch.stack([s["tactile"] for s in pool])))
    torch.testing.assert_close(seen["train"], expected)

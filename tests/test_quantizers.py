"""Tests of the ``vq`` and ``ema_vq`` quantizers (vqtouch.plugins.tokenizer.quantizers)."""

from __future__ import annotations

import math

import pytest
import torch

from vqtouch.core import BuildContext, ConfigError, Quantizer, load, load_plugins, save
from vqtouch.plugins.tokenizer import quantizers as quantizers_module

HOST = load_plugins(autoload=False, extra=["vqtouch.plugins.tokenizer.quantizers"])
LATENT_DIM = 8
CONTEXT = BuildContext(latent_dim=LATENT_DIM)
QUANTIZERS = ["vq", "ema_vq"]


def build(name: str, **options) -> Quantizer:
    """A quantizer built the way users build it, with a fixed seed for its codebook init."""
    torch.manual_seed(options.pop("seed", 0))
    context = options.pop("context", CONTEXT)
    return HOST.build("quantizer", {"name": name, **options}, context)


def randn(*shape: int, seed: int = 1) -> torch.Tensor:
    return torch.randn(*shape, generator=torch.Generator().manual_seed(seed))


def set_codebook(quantizer: Quantizer, codebook_KC: torch.Tensor) -> None:
    """Overwrite the codebook (in eval mode the EMA statistics behind an ema_vq codebook do not matter)."""
    with torch.no_grad():
        quantizer.codebook_KC.copy_(codebook_KC)


def lookup_space_reference(quantizer: Quantizer, latents_BDhw: torch.Tensor):
    """Vectors and codebook in the space codes are chosen in, recomputed independently of the module."""
    vectors_NC = latents_BDhw.permute(0, 2, 3, 1).reshape(-1, latents_BDhw.shape[1]).double()
    codebook_KC = quantizer.codebook_KC.detach().double()
    if quantizer.project_in is not None:
        vectors_NC = vectors_NC @ quantizer.project_in.weight.detach().double().T + quantizer.project_in.bias.detach()
    if quantizer.l2_normalize:
        vectors_NC = vectors_NC / vectors_NC.norm(dim=1, keepdim=True)
        codebook_KC = codebook_KC / codebook_KC.norm(dim=1, keepdim=True)
    return vectors_NC, codebook_KC


LOOKUP_VARIANTS = [
    pytest.param("vq", {}, id="vq"),
    pytest.param("vq", {"l2_normalize": True}, id="vq-cosine"),
    pytest.param("vq", {"lookup_dim": 4}, id="vq-factorised"),
    pytest.param("vq", {"lookup_dim": 4, "l2_normalize": True}, id="vq-factorised-cosine"),
    pytest.param("ema_vq", {}, id="ema_vq"),
    pytest.param("vq", {"rotation_trick": True}, id="vq-rotation"),
    pytest.param("vq", {"rotation_trick": True, "lookup_dim": 4, "l2_normalize": True}, id="vq-rotation-cosine"),
    pytest.param("ema_vq", {"rotation_trick": True}, id="ema_vq-rotation"),
    pytest.param("vq", {"simvq": True}, id="vq-simvq"),  # its map starts as the identity: codebook_KC is the codebook
]


def test_both_quantizers_are_registered():
    assert set(QUANTIZERS) <= set(HOST.registry("quantizer").names())


@pytest.mark.parametrize("name", QUANTIZERS)
def test_output_shapes_and_dtypes(name):
    quantizer = build(name, codebook_size=16)
    assert quantizer.codebook_size == 16 and quantizer.embedding_dim == LATENT_DIM
    output = quantizer(randn(2, LATENT_DIM, 4, 5))
    assert output.quantized_BDhw.shape == (2, LATENT_DIM, 4, 5) and output.quantized_BDhw.dtype == torch.float32
    assert output.codes_Bhw.shape == (2, 4, 5) and output.codes_Bhw.dtype == torch.long
    assert output.loss.shape == () and output.loss.dtype == torch.float32
    assert output.perplexity.shape == () and 1.0 <= float(output.perplexity) <= 16.0


@pytest.mark.parametrize("name, options", LOOKUP_VARIANTS)
def test_codes_are_true_nearest_neighbours(name, options):
    quantizer = build(name, codebook_size=64, init="normal", **options).eval()
    latents_BDhw = randn(3, LATENT_DIM, 6, 7)
    codes_N = quantizer(latents_BDhw).codes_Bhw.reshape(-1)
    vectors_NC, codebook_KC = lookup_space_reference(quantizer, latents_BDhw)
    distances_NK = torch.cdist(vectors_NC, codebook_KC)
    chosen_N = distances_NK.gather(1, codes_N.unsqueeze(1)).squeeze(1)
    torch.testing.assert_close(chosen_N, distances_NK.min(dim=1).values, rtol=0, atol=1e-5)
    assert (codes_N == distances_NK.argmin(dim=1)).float().mean() > 0.99  # ties aside, the same indices


def test_nearest_code_is_exact_for_huge_latents():
    # Both codes are orthogonal to z, so only ||e||^2 separates them (0.25 vs 0.04); adding the
    # per-row ||z||^2 = 1e8 in float32 would round both distances to the same value and tie.
    vectors_NC = torch.zeros(3, LATENT_DIM)
    vectors_NC[:, 0] = torch.tensor([1e4, -1e4, 3e3])
    codebook_KC = torch.zeros(2, LATENT_DIM)
    codebook_KC[0, 1], codebook_KC[1, 1] = 0.5, 0.2
    assert torch.equal(quantizers_module.nearest_codes(vectors_NC, codebook_KC), torch.ones(3, dtype=torch.long))


def test_blockwise_distance_search_matches_one_block(monkeypatch):
    vectors_NC, codebook_KC = randn(300, 5, seed=2), randn(37, 5, seed=3)
    whole_N = quantizers_module.nearest_codes(vectors_NC, codebook_KC)
    monkeypatch.setattr(quantizers_module, "MAX_DISTANCE_ELEMENTS", 37 * 7)  # blocks of 7 rows
    assert torch.equal(quantizers_module.nearest_codes(vectors_NC, codebook_KC), whole_N)


@pytest.mark.parametrize("name", QUANTIZERS)
def test_straight_through_gradient_is_identity(name):
    quantizer = build(name, codebook_size=16)
    latents_BDhw = randn(2, LATENT_DIM, 3, 3).requires_grad_()
    upstream_BDhw = randn(2, LATENT_DIM, 3, 3, seed=5)
    (quantizer(latents_BDhw).quantized_BDhw * upstream_BDhw).sum().backward()
    torch.testing.assert_close(latents_BDhw.grad, upstream_BDhw, rtol=0, atol=0)


@pytest.mark.parametrize("beta", [0.25, 0.7])
def test_vq_loss_weights_codebook_by_one_and_commitment_by_beta(beta):
    # Code 1 is far away, so every latent picks code 0 and the loss gradients have closed forms:
    # dL/de0 = 1 * sum_n 2 (e0 - z_n) / (N D) and dL/dz_n = beta * 2 (z_n - e0) / (N D).
    quantizer = build("vq", codebook_size=2, beta=beta)
    code_0 = randn(LATENT_DIM, seed=7) * 0.1
    set_codebook(quantizer, torch.stack([code_0, torch.full((LATENT_DIM,), 100.0)]))
    latents_BDhw = randn(2, LATENT_DIM, 3, 4).requires_grad_()
    output = quantizer(latents_BDhw)
    assert (output.codes_Bhw == 0).all()
    output.loss.backward()
    vectors_ND = latents_BDhw.detach().permute(0, 2, 3, 1).reshape(-1, LATENT_DIM)
    num_elements = vectors_ND.numel()
    expected_code_grad_D = (2.0 * (code_0 - vectors_ND) / num_elements).sum(dim=0)
    torch.testing.assert_close(quantizer.codebook_KC.grad[0], expected_code_grad_D)
    assert torch.count_nonzero(quantizer.codebook_KC.grad[1]) == 0
    expected_latent_grad_BDhw = beta * 2.0 * (latents_BDhw.detach() - code_0.view(1, -1, 1, 1)) / num_elements
    torch.testing.assert_close(latents_BDhw.grad, expected_latent_grad_BDhw)


def test_ema_loss_is_commitment_only_and_codebook_gets_no_gradient():
    quantizer = build("ema_vq", codebook_size=8, beta=0.4, dead_threshold=0.0)
    assert list(quantizer.parameters()) == [] and not quantizer.codebook_KC.requires_grad
    latents_BDhw = randn(2, LATENT_DIM, 3, 3).requires_grad_()
    codebook_before_KC = quantizer.codebook_KC.clone()
    output = quantizer(latents_BDhw)
    output.loss.backward()
    assert quantizer.codebook_KC.grad is None
    selected_BDhw = codebook_before_KC[output.codes_Bhw].permute(0, 3, 1, 2)
    expected_BDhw = 0.4 * 2.0 * (latents_BDhw.detach() - selected_BDhw) / latents_BDhw.numel()
    torch.testing.assert_close(latents_BDhw.grad, expected_BDhw)


def test_ema_update_follows_the_laplace_smoothed_formula():
    decay, eps = 0.8, 1e-5
    quantizer = build("ema_vq", codebook_size=4, decay=decay, eps=eps, dead_threshold=0.0).train()
    codebook_KD = 10.0 * torch.eye(4, LATENT_DIM)
    cluster_size_K = torch.tensor([1.0, 2.0, 0.5, 3.0])
    embedding_sum_KD = codebook_KD * cluster_size_K.unsqueeze(1)
    with torch.no_grad():
        quantizer.codebook_KC.copy_(codebook_KD)
        quantizer.ema_cluster_size_K.copy_(cluster_size_K)
        quantizer.ema_embedding_sum_KC.copy_(embedding_sum_KD)
    # Five latents near code 0, three near code 1, none near codes 2 and 3.
    vectors_ND = torch.cat([codebook_KD[0] + 0.1 * randn(5, LATENT_DIM), codebook_KD[1] + 0.1 * randn(3, LATENT_DIM)])
    output = quantizer(vectors_ND.view(1, 1, 8, LATENT_DIM).permute(0, 3, 1, 2))
    assert output.codes_Bhw.reshape(-1).tolist() == [0] * 5 + [1] * 3
    counts_K = torch.tensor([5.0, 3.0, 0.0, 0.0])
    sums_KD = torch.zeros(4, LATENT_DIM)
    sums_KD[0], sums_KD[1] = vectors_ND[:5].sum(0), vectors_ND[5:].sum(0)
    expected_size_K = decay * cluster_size_K + (1 - decay) * counts_K
    expected_sum_KD = decay * embedding_sum_KD + (1 - decay) * sums_KD
    total = expected_size_K.sum()
    smoothed_K = (expected_size_K + eps) / (total + 4 * eps) * total
    torch.testing.assert_close(quantizer.ema_cluster_size_K, expected_size_K)
    torch.testing.assert_close(quantizer.ema_embedding_sum_KC, expected_sum_KD)
    torch.testing.assert_close(quantizer.codebook_KC, expected_sum_KD / smoothed_K.unsqueeze(1))


def clustered_latents(
    centres_MD: torch.Tensor, batch: int, side: int, noise: float, generator: torch.Generator
) -> torch.Tensor:
    """Latents (batch, D, side, side), each vector a random centre plus Gaussian noise."""
    count = batch * side * side
    picks = torch.randint(len(centres_MD), (count,), generator=generator)
    vectors_ND = centres_MD[picks] + noise * torch.randn(count, centres_MD.shape[1], generator=generator)
    return vectors_ND.view(batch, side, side, -1).permute(0, 3, 1, 2)


def test_ema_codebook_converges_to_cluster_centres():
    generator = torch.Generator().manual_seed(11)
    centres_MD = 3.0 * torch.randn(4, LATENT_DIM, generator=generator)
    quantizer = build("ema_vq", codebook_size=16, decay=0.9).train()
    for _ in range(150):
        quantizer(clustered_latents(centres_MD, 4, 8, 0.02, generator))
    quantizer.eval()
    codes_N = quantizer(clustered_latents(centres_MD, 4, 8, 0.02, generator)).codes_Bhw.unique()
    used_codes_UD = quantizer.codebook_KC[codes_N]
    distance_to_centres_UM = torch.cdist(used_codes_UD, centres_MD)
    assert distance_to_centres_UM.min(dim=1).values.max() < 0.1  # every used code sits on a centre
    assert distance_to_centres_UM.min(dim=0).values.max() < 0.1  # every centre has a code


def test_ema_dead_codes_restart_on_batch_latents_and_usage_rises():
    generator = torch.Generator().manual_seed(12)
    centres_MD = 5.0 + torch.randn(8, LATENT_DIM, generator=generator)  # far from the tiny initial codes
    quantizer = build("ema_vq", codebook_size=32).eval()
    quantizer(clustered_latents(centres_MD, 4, 8, 0.05, generator))
    usage_before = quantizer.usage_fraction()
    assert usage_before <= 2 / 32

    quantizer.train()
    latents_BDhw = clustered_latents(centres_MD, 4, 8, 0.05, generator)
    first_counts_K = torch.bincount(quantizer.eval()(latents_BDhw).codes_Bhw.reshape(-1), minlength=32)
    quantizer.train()(latents_BDhw)
    batch_vectors_ND = latents_BDhw.permute(0, 2, 3, 1).reshape(-1, LATENT_DIM)
    restarted = first_counts_K < 2  # fewer than dead_threshold = 2 assignments: dead after the first update
    assert restarted.sum() >= 30
    for code_D in quantizer.codebook_KC[restarted]:
        assert (batch_vectors_ND == code_D).all(dim=1).any(), "a restarted code must be a latent of the batch"
    threshold = quantizer.dead_count_threshold
    torch.testing.assert_close(quantizer.ema_cluster_size_K[restarted], torch.full((int(restarted.sum()),), threshold))

    for _ in range(20):
        quantizer(clustered_latents(centres_MD, 4, 8, 0.05, generator))
    quantizer.eval().reset_usage()
    quantizer(clustered_latents(centres_MD, 4, 8, 0.05, generator))
    assert quantizer.usage_fraction() >= 8 / 32 > usage_before


def test_ema_eval_mode_leaves_the_codebook_alone():
    quantizer = build("ema_vq", codebook_size=8).eval()
    before = {key: value.clone() for key, value in quantizer.state_dict().items()}
    quantizer(randn(2, LATENT_DIM, 4, 4))
    for key, value in quantizer.state_dict().items():
        assert torch.equal(value, before[key]), key


@pytest.mark.parametrize("scale", [1.0, 1e4])
@pytest.mark.parametrize("name, options", LOOKUP_VARIANTS)
def test_lookup_of_codes_reproduces_quantized_latents(name, options, scale):
    # At |z| = 1e4 this also checks that the straight-through output is exactly the code vector (the
    # usual z + sg(e - z) would be off by the float32 spacing of z, about 1e-3).
    quantizer = build(name, codebook_size=32, init="normal", **options).eval()  # eval: no EMA update in between
    output = quantizer(scale * randn(2, LATENT_DIM, 5, 3))
    looked_up_BDhw = quantizer.lookup(output.codes_Bhw)
    assert looked_up_BDhw.dtype == torch.float32
    torch.testing.assert_close(looked_up_BDhw, output.quantized_BDhw, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("name", QUANTIZERS)
def test_perplexity_is_one_when_every_latent_is_equal(name):
    quantizer = build(name, codebook_size=16, init="normal").eval()
    output = quantizer(randn(1, LATENT_DIM, 1, 1).expand(3, LATENT_DIM, 4, 4).contiguous())
    assert output.codes_Bhw.unique().numel() == 1
    torch.testing.assert_close(output.perplexity, torch.tensor(1.0))


@pytest.mark.parametrize("name", QUANTIZERS)
def test_perplexity_counts_equally_used_separated_clusters(name):
    num_clusters = 5
    quantizer = build(name, codebook_size=16).eval()
    centres_MD = 10.0 * torch.eye(16, LATENT_DIM)[:num_clusters] + 1.0
    codebook_KD = torch.cat([centres_MD, 100.0 + randn(16 - num_clusters, LATENT_DIM)])
    set_codebook(quantizer, codebook_KD)
    vectors_ND = centres_MD.repeat(4, 1) + 0.01 * randn(4 * num_clusters, LATENT_DIM)
    output = quantizer(vectors_ND.view(1, 4, num_clusters, LATENT_DIM).permute(0, 3, 1, 2))
    torch.testing.assert_close(output.perplexity, torch.tensor(float(num_clusters)))


def test_perplexity_of_a_known_histogram():
    counts_K = torch.tensor([2, 1, 1, 0])
    expected = math.exp(-(0.5 * math.log(0.5) + 2 * 0.25 * math.log(0.25)))
    torch.testing.assert_close(quantizers_module.perplexity_of_counts(counts_K), torch.tensor(expected))


EXTREMES = [
    pytest.param(2, (4, 4, 4), 1.0, id="codebook-of-2"),
    pytest.param(16384, (2, 8, 8), 1.0, id="codebook-of-16384"),
    pytest.param(64, (1, 4, 4), 1.0, id="batch-of-1"),
    pytest.param(64, (2, 4, 4), "constant", id="constant-latents"),
    pytest.param(64, (2, 4, 4), "zeros", id="zero-latents"),  # a zero vector has no direction to normalise
    pytest.param(64, (2, 4, 4), 1e4, id="huge-latents"),
]


@pytest.mark.parametrize("name, options", LOOKUP_VARIANTS)
@pytest.mark.parametrize("codebook_size, grid, scale", EXTREMES)
@pytest.mark.parametrize("training", [True, False], ids=["train", "eval"])
@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_numerical_extremes_stay_finite(name, options, codebook_size, grid, scale, training, precision):
    """Finite outputs, loss, perplexity and gradients, codes in range; under bf16 autocast too, with
    bf16 latents (what a bf16 encoder hands the quantizer)."""
    quantizer = build(name, codebook_size=codebook_size, **options).train(training)
    batch, height, width = grid
    shape = (batch, LATENT_DIM, height, width)
    dtype = torch.bfloat16 if precision == "bf16" else torch.float32
    latents_BDhw = (
        {"constant": lambda: torch.full(shape, 0.5), "zeros": lambda: torch.zeros(shape)}.get(
            scale, lambda: scale * randn(*shape)
        )()
        .to(dtype)
        .requires_grad_()
    )
    for _ in range(2):  # the second call sees the EMA update / restarts of the first
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=precision == "bf16"):
            output = quantizer(latents_BDhw)
    output.loss.backward()
    assert output.quantized_BDhw.dtype == torch.float32
    assert torch.isfinite(output.quantized_BDhw).all()
    assert torch.isfinite(output.loss) and torch.isfinite(output.perplexity)
    assert torch.isfinite(latents_BDhw.grad).all()
    assert int(output.codes_Bhw.min()) >= 0 and int(output.codes_Bhw.max()) < codebook_size


@pytest.mark.parametrize("name, options", LOOKUP_VARIANTS)
def test_bf16_autocast_input_is_quantized_in_fp32(name, options):
    # 512 codes in 8 dimensions: many near-ties, which bf16 distances would resolve differently.
    quantizer = build(name, codebook_size=512, init="normal", **options).eval()
    latents_BDhw = randn(4, LATENT_DIM, 8, 8)
    reference = quantizer(latents_BDhw.bfloat16().float())
    with torch.autocast(device_type="cpu", dtype=torch.bfloat16):
        output = quantizer(latents_BDhw.bfloat16())
    assert output.quantized_BDhw.dtype == torch.float32 and output.loss.dtype == torch.float32
    assert torch.isfinite(output.quantized_BDhw).all() and torch.isfinite(output.loss)
    assert torch.equal(output.codes_Bhw, reference.codes_Bhw)
    torch.testing.assert_close(output.loss, reference.loss)
    quantizer.train()
    with torch.autocast(device_type="cpu", dtype=torch.bfloat16):
        quantizer(latents_BDhw.bfloat16())
    assert all(buffer.dtype in (torch.float32, torch.long) for buffer in quantizer.buffers())


@pytest.mark.parametrize("name", QUANTIZERS)
def test_embedding_dim_comes_from_the_config_or_the_context(name):
    assert HOST.build("quantizer", {"name": name, "embedding_dim": 6}, BuildContext()).embedding_dim == 6
    assert HOST.build("quantizer", {"name": name}, BuildContext(latent_dim=12)).embedding_dim == 12


@pytest.mark.parametrize("name", QUANTIZERS)
@pytest.mark.parametrize(
    "options, context, message",
    [
        ({}, BuildContext(), "embedding_dim"),
        ({"embedding_dim": 4}, BuildContext(latent_dim=8), "embedding_dim=4"),
        ({"codebook_size": 64}, BuildContext(latent_dim=8, codebook_size=128), "codebook_size=64"),
        ({"codebok_size": 64}, CONTEXT, "codebook_size"),
        ({"codebook_size": 1}, CONTEXT, "codebook_size"),
        ({"beta": -1.0}, CONTEXT, "beta"),
        ({"init": "kmeans"}, CONTEXT, "init"),
    ],
)
def test_config_errors_are_config_errors(name, options, context, message):
    with pytest.raises(ConfigError, match=message):
        HOST.build("quantizer", {"name": name, **options}, context)


def test_ema_only_options_are_rejected_by_vq_and_vice_versa():
    with pytest.raises(ConfigError, match="decay"):
        HOST.build("quantizer", {"name": "vq", "decay": 0.9}, CONTEXT)
    with pytest.raises(ConfigError, match="lookup_dim"):
        HOST.build("quantizer", {"name": "ema_vq", "lookup_dim": 4}, CONTEXT)


@pytest.mark.parametrize("name", QUANTIZERS)
@pytest.mark.parametrize(
    "codes",
    [
        torch.tensor([[[0, 16]]]),
        torch.tensor([[[-1, 0]]]),
        torch.zeros(1, 2, 2),  # out of range, float
        torch.zeros(2, 2, dtype=torch.long),
        torch.zeros(1, 2, 2, dtype=torch.bool),  # wrong rank, bool
    ],
    ids=["too-large", "negative", "float", "2-d", "bool"],
)
def test_bad_codes_in_lookup_raise_value_error(name, codes):
    quantizer = build(name, codebook_size=16)
    with pytest.raises(ValueError, match="codes"):
        quantizer.lookup(codes)


@pytest.mark.parametrize("name", QUANTIZERS)
@pytest.mark.parametrize(
    "latents",
    [
        torch.zeros(2, LATENT_DIM, 4),
        torch.zeros(2, LATENT_DIM + 1, 4, 4),
        torch.zeros(2, LATENT_DIM, 4, 4, dtype=torch.long),
        torch.zeros(0, LATENT_DIM, 4, 4),
    ],
    ids=["3-d", "wrong-channels", "integer", "empty"],
)
def test_bad_latents_raise_value_error(name, latents):
    with pytest.raises(ValueError, match="latent"):
        build(name, codebook_size=16)(latents)


@pytest.mark.parametrize("name", QUANTIZERS)
def test_usage_fraction_and_reset(name):
    quantizer = build(name, codebook_size=16).eval()
    assert quantizer.usage_fraction() == 0.0
    set_codebook(quantizer, 10.0 * torch.eye(16, LATENT_DIM) + torch.arange(16.0).view(-1, 1) * 100.0)
    codes_B11 = torch.tensor([0, 3, 3, 5]).view(4, 1, 1)
    quantizer(quantizer.lookup(codes_B11))
    assert quantizer.usage_fraction() == 3 / 16
    quantizer(quantizer.lookup(torch.tensor([[[0, 7]]])))
    assert quantizer.usage_fraction() == 4 / 16  # accumulates until reset
    quantizer.reset_usage()
    assert quantizer.usage_fraction() == 0.0
    assert "usage_counts_K" not in quantizer.state_dict()  # a report, not model state


@pytest.mark.parametrize("name, options", [("vq", {"lookup_dim": 4}), ("ema_vq", {})])
def test_checkpoint_round_trip_after_training(name, options, tmp_path):
    quantizer = build(name, codebook_size=16, **options).train()
    for seed in range(3):
        quantizer(randn(2, LATENT_DIM, 4, 4, seed=seed))
    path = save(quantizer, tmp_path / f"{name}.safetensors", step=3, host=HOST)
    restored = load(path, host=HOST).eval()
    original, loaded = quantizer.state_dict(), restored.state_dict()
    assert original.keys() == loaded.keys()
    for key in original:
        assert torch.equal(original[key], loaded[key]), key
    latents_BDhw = randn(1, LATENT_DIM, 4, 4, seed=9)
    assert torch.equal(quantizer.eval()(latents_BDhw).codes_Bhw, restored(latents_BDhw).codes_Bhw)


@pytest.mark.skipif(not torch.distributed.is_available(), reason="torch.distributed is not built in")
def test_ema_distributed_branch_runs_in_a_single_process_group(tmp_path):
    # World size 1 only exercises the all-reduce / broadcast calls; that two ranks end with identical
    # statistics and restarted codes was checked with a 2-process gloo run outside this fast suite.
    torch.distributed.init_process_group("gloo", init_method=f"file://{tmp_path / 'store'}", rank=0, world_size=1)
    try:
        quantizer = build("ema_vq", codebook_size=16).train()
        reference = build("ema_vq", codebook_size=16).train()
        latents_BDhw = randn(2, LATENT_DIM, 4, 4)
        torch.manual_seed(3)
        quantizer(latents_BDhw)
    finally:
        torch.distributed.destroy_process_group()
    torch.manual_seed(3)
    reference(latents_BDhw)
    for key, value in reference.state_dict().items():
        assert torch.equal(quantizer.state_dict()[key], value), key


def _rotation_reference(z_NC: torch.Tensor, e_NC: torch.Tensor, upstream_NC: torch.Tensor) -> torch.Tensor:
    """The rotation trick's encoder gradient in float64 with explicit D x D matrices: for each row,
    lambda R^T g, R the rotation of z's direction onto e's (R = I - 2 r r^T + 2 e^ u^T)."""
    rows = []
    for z, e, g in zip(z_NC.double(), e_NC.double(), upstream_NC.double()):
        u, e_hat = z / z.norm(), e / e.norm()
        r = (u + e_hat) / (u + e_hat).norm()
        rotation = torch.eye(len(z), dtype=torch.float64) - 2 * torch.outer(r, r) + 2 * torch.outer(e_hat, u)
        torch.testing.assert_close(rotation @ u, e_hat)  # the reference itself: R takes u onto e^
        rows.append(e.norm() / z.norm() * rotation.T @ g)
    return torch.stack(rows)


@pytest.mark.parametrize("name", QUANTIZERS)
def test_the_rotation_trick_keeps_the_codes_and_passes_the_rotated_gradient(name):
    plain = build(name, codebook_size=16)
    rotated = build(name, codebook_size=16, rotation_trick=True)
    latents_BDhw = randn(2, LATENT_DIM, 3, 3).requires_grad_()
    upstream_BDhw = randn(2, LATENT_DIM, 3, 3, seed=5)
    plain_out, out = plain.eval()(latents_BDhw), rotated.eval()(latents_BDhw)
    assert torch.equal(out.codes_Bhw, plain_out.codes_Bhw)
    assert torch.equal(out.quantized_BDhw, plain_out.quantized_BDhw)  # forward values: exactly the codes
    (out.quantized_BDhw * upstream_BDhw).sum().backward(inputs=[latents_BDhw])
    to_rows = lambda t: t.detach().permute(0, 2, 3, 1).reshape(-1, LATENT_DIM)  # noqa: E731
    expected = _rotation_reference(to_rows(latents_BDhw), to_rows(out.quantized_BDhw), to_rows(upstream_BDhw))
    torch.testing.assert_close(to_rows(latents_BDhw.grad).double(), expected, rtol=1e-4, atol=1e-5)
    assert not torch.allclose(to_rows(latents_BDhw.grad), to_rows(upstream_BDhw), atol=1e-3)  # not the identity


def test_the_rotation_trick_keeps_the_identity_gradient_for_a_zero_latent():
    quantizer = build("vq", codebook_size=8, rotation_trick=True).eval()
    latents_BDhw = torch.zeros(1, LATENT_DIM, 2, 2, requires_grad=True)
    upstream_BDhw = randn(1, LATENT_DIM, 2, 2)
    (quantizer(latents_BDhw).quantized_BDhw * upstream_BDhw).sum().backward()
    torch.testing.assert_close(latents_BDhw.grad, upstream_BDhw)


def test_simvq_trains_one_map_that_moves_every_code_and_keeps_the_basis():
    """SimVQ: the basis is a frozen buffer, the map is the one trained parameter of the codebook, and one
    step moves every code (a plain ``vq`` step moves only the codes that were chosen)."""
    results = {}
    for simvq in (False, True):
        quantizer = build("vq", codebook_size=64, init="normal", simvq=simvq).train()
        before_KC = quantizer._lookup_codebook().detach().clone()
        basis_KC = quantizer.codebook_KC.detach().clone()
        optimizer = torch.optim.SGD(quantizer.parameters(), lr=0.5)
        output = quantizer(randn(1, LATENT_DIM, 2, 2))  # 4 latents: at most 4 of the 64 codes chosen
        output.loss.backward()
        optimizer.step()
        moved_K = (quantizer._lookup_codebook().detach() - before_KC).norm(dim=1) > 1e-6
        results[simvq] = (int(moved_K.sum()), torch.equal(quantizer.codebook_KC, basis_KC))
        if simvq:
            assert "codebook_KC" not in dict(quantizer.named_parameters())
            assert "codebook_KC" in quantizer.state_dict()  # the basis is saved with the map
            codes_Bhw = torch.tensor([[[0, 5], [63, 7]]])
            expected_KC = basis_KC @ quantizer.codebook_map.weight.detach().T
            torch.testing.assert_close(
                quantizer.lookup(codes_Bhw)[0].permute(1, 2, 0).reshape(4, -1), expected_KC[codes_Bhw.reshape(-1)]
            )
    assert results[False][0] <= 4 and not results[False][1]
    assert results[True] == (64, True)

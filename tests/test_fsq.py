"""The ``fsq`` quantizer (vqtouch.plugins.tokenizer.fsq): the grid, its codes, the straight-through
gradient, the contract, save/load and the numerical extremes."""

from __future__ import annotations

import itertools
import math

import pytest
import torch

from vqtouch.core import BuildContext, ConfigError, load, load_plugins, save
from vqtouch.plugins.testing import check_plugin

HOST = load_plugins(autoload=False, extra=["vqtouch.plugins.tokenizer.fsq"])
LATENT_DIM = 8
CONTEXT = BuildContext(latent_dim=LATENT_DIM)


def build(levels=(8, 5, 5, 5), context=CONTEXT, seed=0):
    torch.manual_seed(seed)
    return HOST.build("quantizer", {"name": "fsq", "levels": list(levels)}, context)


def randn(*shape: int, seed: int = 1) -> torch.Tensor:
    return torch.randn(*shape, generator=torch.Generator().manual_seed(seed))


def test_fsq_keeps_the_quantizer_contract():
    check_plugin(HOST, "quantizer", "fsq", {"levels": [4, 3, 2]}, CONTEXT)


@pytest.mark.parametrize("levels", [(8, 5, 5, 5), (2, 3), (7, 4, 2)])
def test_every_code_is_a_grid_point_and_lookup_inverts_it(levels):
    """lookup enumerates prod(levels) distinct grid points; each, pushed back through the bound
    (its pre-image), gets its own code again."""
    quantizer = build(levels).eval()
    assert quantizer.codebook_size == math.prod(levels)
    codes_K = torch.arange(quantizer.codebook_size).view(1, 1, -1)
    # Every code's digits, first level fastest, recomputed here independently of the module.
    digits = torch.tensor([combo[::-1] for combo in itertools.product(*[range(n) for n in levels[::-1]])])
    half = torch.tensor([n // 2 for n in levels], dtype=torch.float32)
    grid_Kd = (digits.float() - half) / half
    expected = torch.nn.functional.linear(grid_Kd, quantizer.project_out.weight, quantizer.project_out.bias)
    looked_up_K_D = quantizer.lookup(codes_K)[0].permute(1, 2, 0).reshape(-1, LATENT_DIM)
    torch.testing.assert_close(looked_up_K_D, expected)
    assert len({tuple(row) for row in grid_Kd.tolist()}) == quantizer.codebook_size


def test_forward_codes_follow_the_rounded_bounded_projection():
    quantizer = build((8, 5, 5, 5)).eval()
    latents_BDhw = 3 * randn(4, LATENT_DIM, 4, 4)
    output = quantizer(latents_BDhw)
    projected_Nd = torch.nn.functional.linear(
        latents_BDhw.permute(0, 2, 3, 1).reshape(-1, LATENT_DIM).double(),
        quantizer.project_in.weight.double(),
        quantizer.project_in.bias.double(),
    )
    levels = torch.tensor([8, 5, 5, 5], dtype=torch.float64)
    half = (levels - 1) * 1.001 / 2
    offset = (levels % 2 == 0).double() * 0.5
    bounded = torch.tanh(projected_Nd + torch.atanh(offset / half)) * half - offset
    digits = bounded.round() + torch.div(levels, 2, rounding_mode="floor")
    codes = (digits * torch.tensor([1, 8, 40, 200], dtype=torch.float64)).sum(1).long()
    assert torch.equal(output.codes_Bhw.reshape(-1), codes)
    assert torch.equal(quantizer.lookup(output.codes_Bhw), output.quantized_BDhw)
    assert float(output.loss) == 0.0


def test_the_straight_through_gradient_is_the_bound_s_derivative():
    """d(quantized)/d(latents) is that of the un-rounded path: rounding passes gradients unchanged."""
    quantizer = build((8, 5, 5, 5)).eval()
    latents_BDhw = randn(2, LATENT_DIM, 2, 2).requires_grad_()
    upstream_BDhw = randn(2, LATENT_DIM, 2, 2, seed=3)
    (quantizer(latents_BDhw).quantized_BDhw * upstream_BDhw).sum().backward()

    def smooth(latents):
        vectors = latents.permute(0, 2, 3, 1).reshape(-1, LATENT_DIM)
        bounded = quantizer._bound(quantizer.project_in(vectors))
        half = torch.div(quantizer.levels_d, 2, rounding_mode="floor")
        return quantizer.project_out(bounded / half).view(2, 2, 2, LATENT_DIM).permute(0, 3, 1, 2)

    reference = latents_BDhw.detach().clone().requires_grad_()
    (smooth(reference) * upstream_BDhw).sum().backward()
    torch.testing.assert_close(latents_BDhw.grad, reference.grad)


def test_usage_reaches_most_codes_on_spread_latents():
    quantizer = build((4, 4, 4)).eval()
    quantizer.reset_usage()
    quantizer(4 * randn(16, LATENT_DIM, 8, 8))
    assert float((quantizer.usage_counts() > 0).float().mean()) > 0.8


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
@pytest.mark.parametrize(
    "levels, shape, fill",
    [
        ((2,), (2, LATENT_DIM, 4, 4), "random"),  # two codes
        ((16, 16, 16, 16), (1, LATENT_DIM, 4, 4), "random"),  # 65536 codes, batch 1
        ((8, 5, 5, 5), (2, LATENT_DIM, 4, 4), "constant"),
        ((8, 5, 5, 5), (2, LATENT_DIM, 4, 4), "zeros"),
        ((8, 5, 5, 5), (2, LATENT_DIM, 4, 4), "huge"),
    ],
)
def test_numerical_extremes_stay_finite(levels, shape, fill, precision):
    quantizer = build(levels).train()
    dtype = torch.bfloat16 if precision == "bf16" else torch.float32
    latents = (
        {
            "random": lambda: randn(*shape),
            "constant": lambda: torch.full(shape, 0.5),
            "zeros": lambda: torch.zeros(shape),
            "huge": lambda: 1e4 * randn(*shape),
        }[fill]()
        .to(dtype)
        .requires_grad_()
    )
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=precision == "bf16"):
        output = quantizer(latents)
    output.quantized_BDhw.sum().backward()
    assert output.quantized_BDhw.dtype == torch.float32 and torch.isfinite(output.quantized_BDhw).all()
    assert torch.isfinite(output.perplexity) and torch.isfinite(latents.grad).all()
    assert 0 <= int(output.codes_Bhw.min()) and int(output.codes_Bhw.max()) < quantizer.codebook_size


def test_save_and_load_round_trip(tmp_path):
    quantizer = build((7, 4, 2), seed=4).eval()
    path = save(quantizer, tmp_path / "fsq.safetensors", step=0, host=HOST)
    restored = load(path, host=HOST).eval()
    latents_BDhw = randn(2, LATENT_DIM, 3, 3, seed=7)
    assert restored.levels == (7, 4, 2)
    assert torch.equal(restored(latents_BDhw).codes_Bhw, quantizer(latents_BDhw).codes_Bhw)
    assert torch.equal(restored(latents_BDhw).quantized_BDhw, quantizer(latents_BDhw).quantized_BDhw)


@pytest.mark.parametrize(
    "options, context, message",
    [
        ({"levels": [1, 5]}, CONTEXT, r"every level must be in \[2, 256\]"),
        ({"levels": [256, 256, 2]}, CONTEXT, "make 131072 codes; at most 65536"),
        ({"levels": [8, 8]}, BuildContext(latent_dim=8, codebook_size=1000), "make 64 codes but the experiment"),
        ({"levels": [8, 8]}, BuildContext(), "needs the latent width"),
    ],
)
def test_bad_settings_are_one_line_errors(options, context, message):
    with pytest.raises(ConfigError, match=message):
        HOST.build("quantizer", {"name": "fsq", **options}, context)


def test_bad_codes_and_latents_are_refused():
    quantizer = build((4, 4))
    with pytest.raises(ValueError, match=r"codes must be in \[0, 16\)"):
        quantizer.lookup(torch.tensor([[[16]]]))
    with pytest.raises(ValueError, match="integer codes"):
        quantizer.lookup(torch.zeros(1, 1, 1))
    with pytest.raises(ValueError, match=r"latents of shape \(B, 8, h, w\)"):
        quantizer(torch.zeros(1, 3, 2, 2))


def test_a_generator_trains_and_samples_over_fsq_codes(tmp_path):
    """Codes are codes: the tiny label-to-touch run (tokenizer, then generator) with ``fsq`` in place
    of ``vq``, then ``vqtouch generate`` from it."""
    import generator_runs
    from PIL import Image

    from vqtouch.plugins.cli.app import main

    run = tmp_path / "run"
    quantizer = 'tokenizer.quantizer={"name": "fsq", "levels": [4, 4, 2]}'  # 32 codes, the tiny run's count
    tiny = [override for override in generator_runs.TINY if not override.startswith("tokenizer.quantizer.")]
    overrides = [item for override in (quantizer, *tiny) for item in ("--set", override)]
    train = ["--no-progress", "train", "generator", "--scene", "label-to-touch", "--out", str(run)]
    assert main([*train, *overrides]) == 0
    assert load(next((run / "checkpoints").glob("step-*/quantizer.safetensors")), host=HOST).levels == (4, 4, 2)
    out = tmp_path / "generated"
    assert main(["--no-progress", "generate", "--run", str(run), "--label", "1", "--n", "2", "--steps", "3",
                 "--out", str(out)]) == 0  # fmt: skip
    images = sorted(out.glob("sample_*.png"))
    assert len(images) == 2 and all(Image.open(path).size == (32, 32) for path in images)

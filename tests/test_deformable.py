"""Deformable convolution: torchvision parity, identity at init, gradients, bounds and dtypes.

torchvision is optional here: without an importable ``torchvision.ops`` only the tests of the
torchvision backend and the parity checks against it skip; the pure-PyTorch backends (gather,
the default, and grid_sample) are still tested in full.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from vqtouch.plugins.tokenizer.deformable import (
    DeformableConv2d,
    bilinear_taps,
    deform_conv2d_gather,
    deform_conv2d_grid_sample,
    deform_conv2d_torchvision,
)


def _import_torchvision_ops():
    """``torchvision.ops``, or None when it cannot be imported (absent, or a build that fails to load)."""
    try:
        import torchvision.ops
    except (ImportError, OSError, RuntimeError):
        return None
    return torchvision.ops


torchvision_ops = _import_torchvision_ops()
needs_torchvision = pytest.mark.skipif(
    torchvision_ops is None,
    reason="torchvision.ops is not importable: torchvision-backend test skipped "
    "(the pure-PyTorch backends are tested without it)",
)
# Parametrisations over both backends: only the torchvision case carries the skip.
BACKENDS = ["grid_sample", "gather", pytest.param("torchvision", marks=needs_torchvision)]
FUNCTIONS = [
    pytest.param(deform_conv2d_grid_sample, id="grid_sample"),
    pytest.param(deform_conv2d_gather, id="gather"),
    pytest.param(deform_conv2d_torchvision, id="torchvision", marks=needs_torchvision),
]
PURE_FUNCTIONS = [
    pytest.param(deform_conv2d_grid_sample, id="grid_sample"),
    pytest.param(deform_conv2d_gather, id="gather"),
]

HEIGHT, WIDTH = 9, 11  # non-square on purpose: catches (dy, dx) / (x, y) swaps


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """Tiny tensors gain nothing from intra-op threads, and on a shared 2-core machine OpenMP
    with busy cores made single calls 10-100x slower; restored for the rest of the session."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def out_size(size: int, kernel: int, stride: int, padding: int, dilation: int) -> int:
    return (size + 2 * padding - dilation * (kernel - 1) - 1) // stride + 1


def random_problem(
    kernel=3,
    stride=1,
    padding=1,
    dilation=1,
    with_mask=True,
    offset_groups=1,
    in_channels=4,
    out_channels=6,
    batch=2,
    offset_scale=3.0,
    dtype=torch.float32,
    seed=0,
):
    """Input, offset, weight, bias, mask with random non-integer offsets, some far outside the image."""
    generator = torch.Generator().manual_seed(seed)
    out_h = out_size(HEIGHT, kernel, stride, padding, dilation)
    out_w = out_size(WIDTH, kernel, stride, padding, dilation)
    taps = kernel * kernel
    x = torch.randn(batch, in_channels, HEIGHT, WIDTH, generator=generator, dtype=dtype)
    offset = offset_scale * torch.randn(batch, 2 * offset_groups * taps, out_h, out_w, generator=generator, dtype=dtype)
    weight = torch.randn(out_channels, in_channels, kernel, kernel, generator=generator, dtype=dtype)
    bias = torch.randn(out_channels, generator=generator, dtype=dtype)
    mask = (
        torch.rand(batch, offset_groups * taps, out_h, out_w, generator=generator, dtype=dtype) if with_mask else None
    )
    return x, offset, weight, bias, mask


# -- forward parity with torchvision --------------------------------------------------------


@pytest.mark.parametrize("kernel", [3, 1])
@pytest.mark.parametrize("stride", [1, 2])
@pytest.mark.parametrize("padding", [0, 1, 2])
@pytest.mark.parametrize("dilation", [1, 2])
@pytest.mark.parametrize("with_mask", [True, False])
@needs_torchvision
def test_grid_sample_matches_torchvision(kernel, stride, padding, dilation, with_mask):
    x, offset, weight, bias, mask = random_problem(kernel, stride, padding, dilation, with_mask)
    # The offsets must exercise the boundary: some taps land outside the image.
    assert offset.abs().max() > WIDTH / 2
    assert not torch.equal(offset, offset.round())
    ours = deform_conv2d_grid_sample(x, offset, weight, bias, stride, padding, dilation, mask)
    reference = torchvision_ops.deform_conv2d(
        x, offset, weight, bias, stride=stride, padding=padding, dilation=dilation, mask=mask
    )
    assert ours.shape == reference.shape
    torch.testing.assert_close(ours, reference, atol=1e-4, rtol=1e-4)


@needs_torchvision
def test_offset_groups_weight_groups_and_pair_arguments_match_torchvision():
    generator = torch.Generator().manual_seed(1)
    out_h, out_w = out_size(HEIGHT, 3, 1, 1, 1), out_size(WIDTH, 3, 2, 2, 1)
    x = torch.randn(2, 4, HEIGHT, WIDTH, generator=generator)
    offset = 2.5 * torch.randn(2, 2 * 2 * 9, out_h, out_w, generator=generator)  # 2 offset groups
    mask = torch.rand(2, 2 * 9, out_h, out_w, generator=generator)
    grouped_weight = torch.randn(6, 2, 3, 3, generator=generator)  # 2 weight groups of 2 input channels
    bias = torch.randn(6, generator=generator)
    ours = deform_conv2d_grid_sample(x, offset, grouped_weight, bias, (1, 2), (1, 2), (1, 1), mask)
    reference = torchvision_ops.deform_conv2d(x, offset, grouped_weight, bias, stride=(1, 2), padding=(1, 2), mask=mask)
    torch.testing.assert_close(ours, reference, atol=1e-4, rtol=1e-4)


@pytest.mark.parametrize("function", FUNCTIONS)
@pytest.mark.parametrize("stride,padding,dilation", [(1, 1, 1), (2, 0, 1), (1, 2, 2), (2, 1, 2)])
def test_zero_offsets_and_unit_mask_equal_conv2d(stride, padding, dilation, function):
    x, offset, weight, bias, mask = random_problem(3, stride, padding, dilation)
    offset, mask = torch.zeros_like(offset), torch.ones_like(mask)
    expected = F.conv2d(x, weight, bias, stride=stride, padding=padding, dilation=dilation)
    torch.testing.assert_close(
        function(x, offset, weight, bias, stride, padding, dilation, mask), expected, atol=1e-5, rtol=1e-5
    )
    torch.testing.assert_close(
        function(x, offset, weight, bias, stride, padding, dilation, None), expected, atol=1e-5, rtol=1e-5
    )


# -- the layer ---------------------------------------------------------------------------------


@pytest.mark.parametrize("modulation", [True, False])
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("stride,padding", [(1, 1), (2, 0)])
def test_layer_at_init_equals_plain_conv(modulation, backend, stride, padding):
    layer = DeformableConv2d(5, 8, stride=stride, padding=padding, modulation=modulation, backend=backend)
    x = torch.randn(2, 5, HEIGHT, WIDTH)
    expected = F.conv2d(x, layer.weight, layer.bias, stride=stride, padding=padding)
    torch.testing.assert_close(layer(x), expected, atol=1e-5, rtol=1e-5)
    offset, mask = layer.offsets_and_mask(x)
    assert torch.count_nonzero(offset) == 0
    assert (mask is None) == (not modulation)
    if mask is not None:
        assert torch.equal(mask, torch.ones_like(mask))  # 2 * sigmoid(0) == 1 exactly
    assert layer.last_mean_abs_offset == 0.0


def offset_grouped_layer() -> tuple[DeformableConv2d, torch.Tensor]:
    """A bias-free layer with 2 offset groups (checked to be the plain convolution at init) whose
    offset branch has then left its zero init, and an input."""
    torch.manual_seed(11)
    layer = DeformableConv2d(4, 6, groups=2, bias=False)
    x = torch.randn(2, 4, HEIGHT, WIDTH)
    torch.testing.assert_close(layer(x), F.conv2d(x, layer.weight, None, padding=1), atol=1e-5, rtol=1e-5)
    with torch.no_grad():
        layer.offset_conv.weight.normal_(0, 0.3)
    return layer, x


def test_layer_without_bias_and_offset_groups():
    layer, x = offset_grouped_layer()
    offset, mask = layer.offsets_and_mask(x)
    assert offset.shape == (2, 2 * 2 * 9, HEIGHT, WIDTH) and mask.shape == (2, 2 * 9, HEIGHT, WIDTH)
    assert torch.count_nonzero(offset) > 0
    out = layer(x)
    assert out.shape == (2, 6, HEIGHT, WIDTH) and torch.isfinite(out).all()


@needs_torchvision
def test_layer_with_offset_groups_matches_torchvision():
    layer, x = offset_grouped_layer()
    offset, mask = layer.offsets_and_mask(x)
    reference = torchvision_ops.deform_conv2d(x, offset, layer.weight, None, padding=1, mask=mask)
    torch.testing.assert_close(layer(x), reference, atol=1e-4, rtol=1e-4)


def test_last_mean_abs_offset_reports_detached_float():
    layer = DeformableConv2d(4, 4)
    assert layer.last_mean_abs_offset is None
    with torch.no_grad():
        layer.offset_conv.bias.uniform_(-1, 1)
    x = torch.randn(2, 4, HEIGHT, WIDTH)
    layer(x).sum().backward()
    offset, _ = layer.offsets_and_mask(x)
    value = layer.last_mean_abs_offset
    assert isinstance(value, float)
    assert value == pytest.approx(offset.abs().mean().item(), rel=1e-6)
    assert not layer._last_mean_abs_offset.requires_grad


def test_trained_offsets_get_gradients():
    """Zero-init must not freeze the branch: the offset conv gets a non-zero gradient at init."""
    layer = DeformableConv2d(4, 4)
    x = torch.randn(2, 4, HEIGHT, WIDTH)
    (layer(x) ** 2).sum().backward()
    assert layer.offset_conv.weight.grad.abs().sum() > 0
    assert all(p is layer.offset_conv.weight or p is layer.offset_conv.bias for p in layer.offset_parameters())


# -- gradients ---------------------------------------------------------------------------------


def off_integer_problem(stride: int, with_mask: bool):
    """Float64 problem whose sample positions all sit 0.2-0.8 px from any integer (bilinear
    interpolation has kinks at integer positions, where finite differences disagree with autograd)."""
    generator = torch.Generator().manual_seed(3)
    height, width, kernel = 4, 5, 3
    out_h, out_w = out_size(height, kernel, stride, 1, 1), out_size(width, kernel, stride, 1, 1)
    x = torch.randn(1, 2, height, width, generator=generator, dtype=torch.float64)
    whole = torch.randint(-2, 3, (1, 18, out_h, out_w), generator=generator).double()
    fraction = 0.2 + 0.6 * torch.rand(1, 18, out_h, out_w, generator=generator, dtype=torch.float64)
    offset = whole + fraction
    weight = torch.randn(2, 2, kernel, kernel, generator=generator, dtype=torch.float64)
    bias = torch.randn(2, generator=generator, dtype=torch.float64)
    mask = torch.rand(1, 9, out_h, out_w, generator=generator, dtype=torch.float64) if with_mask else None
    return x, offset, weight, bias, mask


@pytest.mark.parametrize("stride", [1, 2])
@pytest.mark.parametrize("with_mask", [True, False])
@pytest.mark.parametrize("deform_conv2d", PURE_FUNCTIONS)
def test_gradcheck_pure_pytorch_paths(stride, with_mask, deform_conv2d):
    x, offset, weight, bias, mask = off_integer_problem(stride, with_mask)
    inputs = [t.requires_grad_() for t in (x, offset, weight, bias) + ((mask,) if with_mask else ())]

    def function(x, offset, weight, bias, mask=None):
        return deform_conv2d(x, offset, weight, bias, stride=stride, padding=1, mask=mask)

    assert torch.autograd.gradcheck(function, inputs, eps=1e-6, atol=1e-6)


@pytest.mark.parametrize("with_mask", [True, False])
@pytest.mark.parametrize("stride,padding,dilation", [(1, 1, 1), (2, 0, 2)])
@needs_torchvision
def test_backends_agree_on_gradients(with_mask, stride, padding, dilation):
    x, offset, weight, bias, mask = random_problem(3, stride, padding, dilation, with_mask, seed=5)
    gradients = []
    for function in (deform_conv2d_grid_sample, deform_conv2d_torchvision):
        leaves = [t.detach().clone().requires_grad_() for t in (x, offset, weight, bias)]
        leaf_mask = mask.detach().clone().requires_grad_() if with_mask else None
        out = function(*leaves, stride=stride, padding=padding, dilation=dilation, mask=leaf_mask)
        upstream = torch.linspace(-1, 1, out.numel()).view_as(out)
        (out * upstream).sum().backward()
        gradients.append([t.grad for t in leaves] + ([leaf_mask.grad] if with_mask else []))
    for ours, reference in zip(*gradients):
        torch.testing.assert_close(ours, reference, atol=1e-4, rtol=1e-4)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_bilinear_taps_matches_an_indexing_reference(dtype):
    """The gather under the gather backend, values and both gradients, against plain indexing and
    autograd: repeated rows inside a bag, rows read by many bags and rows nobody reads (gradient 0)."""
    generator = torch.Generator().manual_seed(3)
    rows = torch.randn(10, 5, generator=generator, dtype=dtype)
    index = torch.randint(0, 7, (13, 4), generator=generator)  # rows 7-9 are never read
    index[0] = torch.tensor([2, 2, 2, 5])
    factor = torch.randn(13, 4, generator=generator, dtype=dtype)
    upstream = torch.randn(13, 5, generator=generator, dtype=dtype)
    results = []
    for function in (bilinear_taps, lambda r, i, f: (r[i] * f[..., None]).sum(1)):
        leaf_rows, leaf_factor = rows.clone().requires_grad_(), factor.clone().requires_grad_()
        out = function(leaf_rows, index, leaf_factor)
        (out * upstream).sum().backward()
        results.append((out, leaf_rows.grad, leaf_factor.grad))
    for ours, reference in zip(*results):
        torch.testing.assert_close(ours, reference)
    assert not results[0][1][7:].any()


@pytest.mark.parametrize("kernel,stride,padding,dilation", [(3, 1, 1, 1), (3, 2, 0, 2), (1, 1, 0, 1), (3, 1, 2, 1)])
@pytest.mark.parametrize("with_mask", [True, False])
@pytest.mark.parametrize("offset_groups", [1, 2])
def test_gather_backend_equals_grid_sample_in_float32(kernel, stride, padding, dilation, with_mask, offset_groups):
    """The channels-last gather backend and the grid_sample backend agree to 1e-5 in fp32 (relative
    to the largest value), values and gradients, with taps outside the image, offset groups and
    weight groups."""
    generator = torch.Generator().manual_seed(11)
    in_channels, out_channels, weight_groups = 4, 6, 2
    out_h, out_w = (
        out_size(HEIGHT, kernel, stride, padding, dilation),
        out_size(WIDTH, kernel, stride, padding, dilation),
    )
    x = torch.randn(2, in_channels, HEIGHT, WIDTH, generator=generator)
    offset = 4 * torch.randn(2, 2 * offset_groups * kernel * kernel, out_h, out_w, generator=generator)
    weight = torch.randn(out_channels, in_channels // weight_groups, kernel, kernel, generator=generator)
    bias = torch.randn(out_channels, generator=generator)
    mask = torch.rand(2, offset_groups * kernel * kernel, out_h, out_w, generator=generator) if with_mask else None
    results = []
    for function in (deform_conv2d_grid_sample, deform_conv2d_gather):
        leaves = [t.detach().clone().requires_grad_() for t in (x, offset, weight, bias)]
        leaf_mask = mask.detach().clone().requires_grad_() if with_mask else None
        out = function(*leaves, stride=stride, padding=padding, dilation=dilation, mask=leaf_mask)
        (out * torch.linspace(-1, 1, out.numel()).view_as(out)).sum().backward()
        results.append([out.detach()] + [t.grad for t in leaves] + ([leaf_mask.grad] if with_mask else []))
    for reference, gathered in zip(*results):
        scale = max(1.0, float(reference.abs().max()))
        torch.testing.assert_close(gathered, reference, atol=1e-5 * scale, rtol=1e-5)


# -- stability ---------------------------------------------------------------------------------


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("modulation", [True, False])
def test_huge_raw_offsets_stay_bounded_and_finite(backend, modulation):
    layer = DeformableConv2d(4, 4, modulation=modulation, max_offset=3.0, backend=backend)
    with torch.no_grad():
        layer.offset_conv.bias.fill_(1e6)
    x = torch.randn(2, 4, HEIGHT, WIDTH, requires_grad=True)
    out = layer(x)
    assert torch.isfinite(out).all()
    offset, mask = layer.offsets_and_mask(x)
    assert offset.abs().max() <= 3.0
    assert layer.last_mean_abs_offset == pytest.approx(3.0)
    if mask is not None:
        assert mask.max() <= 2.0
    out.square().mean().backward()
    assert torch.isfinite(x.grad).all() and torch.isfinite(layer.weight.grad).all()
    assert torch.isfinite(layer.offset_conv.weight.grad).all()


@pytest.mark.parametrize("deform_conv2d", PURE_FUNCTIONS)
def test_nan_offsets_give_nan_where_they_sample_and_nothing_else(deform_conv2d):
    """NaN weights must surface as NaN outputs (which the evaluation refuses with its own message),
    never as an index error deep in a backend or as finite garbage."""
    x = torch.randn(2, 4, HEIGHT, WIDTH)
    offset = torch.zeros(2, 18, HEIGHT, WIDTH)
    offset[0, :, 3, 5] = float("nan")  # one output pixel of the first image
    out = deform_conv2d(x, offset, torch.randn(6, 4, 3, 3), padding=1, mask=torch.ones(2, 9, HEIGHT, WIDTH))
    nan = torch.isnan(out)
    assert nan[0, :, 3, 5].all()
    nan[0, :, 3, 5] = False
    assert not nan.any()


def scrambled_layer(backend: str, modulation: bool = True) -> DeformableConv2d:
    """A layer whose offset branch is no longer at its zero init (as after some training)."""
    torch.manual_seed(7)
    layer = DeformableConv2d(4, 6, modulation=modulation, backend=backend)
    with torch.no_grad():
        layer.offset_conv.weight.normal_(0, 0.5)
        layer.offset_conv.bias.normal_(0, 1.0)
    return layer


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("fill", [0.0, 1.0, -1.0])
def test_constant_and_saturated_inputs_batch_one(backend, fill):
    layer = scrambled_layer(backend)
    x = torch.full((1, 4, HEIGHT, WIDTH), fill, requires_grad=True)
    out = layer(x)
    assert out.shape == (1, 6, HEIGHT, WIDTH)
    assert torch.isfinite(out).all()
    out.sum().backward()
    assert torch.isfinite(x.grad).all() and torch.isfinite(layer.offset_conv.weight.grad).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_bfloat16_autocast_on_cpu(backend):
    layer = scrambled_layer(backend)
    x = torch.randn(2, 4, HEIGHT, WIDTH)
    reference = layer(x)
    x_leaf = x.clone().requires_grad_()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = layer(x_leaf)
    assert out.dtype == torch.bfloat16
    assert torch.isfinite(out).all()
    scale = reference.abs().max().item()
    torch.testing.assert_close(out.float(), reference, atol=1.5e-2 * scale, rtol=1.5e-2)
    out.float().square().mean().backward()
    assert torch.isfinite(x_leaf.grad).all() and torch.isfinite(layer.offset_conv.weight.grad).all()


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float64])
def test_layer_cast_to_other_dtypes(backend, dtype):
    layer = scrambled_layer(backend)
    x = torch.randn(2, 4, HEIGHT, WIDTH)
    reference = layer(x)
    layer = layer.to(dtype)
    out = layer(x.to(dtype))
    assert out.dtype == dtype and torch.isfinite(out).all()
    tolerance = 5e-2 * reference.abs().max().item() if dtype == torch.bfloat16 else 1e-5
    torch.testing.assert_close(out.float(), reference, atol=tolerance, rtol=5e-2)


# -- errors and imports ------------------------------------------------------------------------


def test_layer_rejects_bad_inputs():
    layer = DeformableConv2d(4, 6)
    with pytest.raises(ValueError, match="4-D input"):
        layer(torch.randn(4, HEIGHT, WIDTH))
    with pytest.raises(ValueError, match="expected 4 input channels, got 3"):
        layer(torch.randn(2, 3, HEIGHT, WIDTH))
    with pytest.raises(ValueError, match="too small"):
        DeformableConv2d(4, 6, padding=0, dilation=4)(torch.randn(1, 4, 5, 5))


def test_constructor_rejects_bad_arguments():
    with pytest.raises(ValueError, match="backend"):
        DeformableConv2d(4, 4, backend="cuda_magic")
    with pytest.raises(ValueError, match="max_offset"):
        DeformableConv2d(4, 4, max_offset=0.0)
    with pytest.raises(ValueError, match="max_offset"):
        DeformableConv2d(4, 4, max_offset=float("inf"))
    with pytest.raises(ValueError, match="offset groups"):
        DeformableConv2d(4, 4, groups=3)
    with pytest.raises(ValueError, match="kernel_size"):
        DeformableConv2d(4, 4, kernel_size=(3, 3, 3))


@pytest.mark.parametrize("function", FUNCTIONS)
def test_functions_reject_bad_shapes(function):
    x, offset, weight, bias, mask = random_problem()
    with pytest.raises(ValueError, match="input must be"):
        function(x[0], offset, weight, bias, mask=mask)
    with pytest.raises(ValueError, match="offset spatial size"):
        function(x, offset[..., :-1], weight, bias, padding=1, mask=mask)
    with pytest.raises(ValueError, match="offset must be"):
        function(x, offset[:, :-1], weight, bias, padding=1, mask=mask)
    with pytest.raises(ValueError, match="mask must be"):
        function(x, offset, weight, bias, padding=1, mask=mask[:, :-1])
    with pytest.raises(ValueError, match="not a multiple"):
        function(x, offset, weight[:, :3], bias, padding=1, mask=mask)
    with pytest.raises(ValueError, match="bias must be"):
        function(x, offset, weight, bias[:-1], padding=1, mask=mask)


def test_importing_the_module_does_not_import_torchvision():
    code = (
        "import sys, vqtouch.plugins.tokenizer.deformable as d; "
        "assert 'torchvision' not in sys.modules, sorted(m for m in sys.modules if 'torchvision' in m)[:5]"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_without_torchvision_only_the_torchvision_tests_skip():
    """Run a few of this file's tests in a fresh interpreter where ``import torchvision.ops`` fails."""
    selection = "test_layer_at_init_equals_plain_conv or test_functions_reject_bad_shapes"
    code = (
        "import sys; sys.modules['torchvision'] = None; sys.modules['torchvision.ops'] = None; import pytest; "
        f"raise SystemExit(pytest.main([{__file__!r}, '-q', '-rs', '-p', 'no:cacheprovider', "
        f"'-k', {selection!r}]))"
    )
    completed = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=Path(__file__).resolve().parent.parent,
        env=dict(os.environ),
    )
    assert completed.returncode == 0, completed.stdout[-3000:] + completed.stderr[-2000:]
    counts = dict(
        (word, int(number))
        for number, word in re.findall(
            r"(\d+) (passed|skipped|failed|error)", completed.stdout.strip().splitlines()[-1]
        )
    )
    # Every grid_sample and gather case runs and passes; exactly their torchvision twin skips, with the reason.
    assert counts.get("passed", 0) == 2 * counts.get("skipped", 0) > 0 and set(counts) == {"passed", "skipped"}, counts
    assert "torchvision.ops is not importable" in completed.stdout


def test_torchvision_backend_without_torchvision_fails_when_built(monkeypatch):
    """A missing torchvision is reported when the model is built, with the fix, not mid-training."""
    import importlib.util

    from vqtouch.core import ConfigError
    from vqtouch.plugins.tokenizer.deformable import DeformableConv2d

    real_find_spec = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "torchvision" else real_find_spec(name, *a)
    )
    with pytest.raises(
        ConfigError,
        match=r"deformable_backend 'torchvision' needs torchvision, which is not "
        r"installed: pip install torchvision",
    ):
        DeformableConv2d(4, 4, 3, padding=1, backend="torchvision")
    DeformableConv2d(4, 4, 3, padding=1)  # the default (gather) needs nothing
    DeformableConv2d(4, 4, 3, padding=1, backend="grid_sample")

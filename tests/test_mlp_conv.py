"""The generator's optional depthwise convolution inside each block's MLP (``generator.model.mlp_conv``)."""

from __future__ import annotations

import pytest
import torch
from pydantic import ValidationError

from vqtouch.plugins.generator.denoiser import DiffusionTransformer
from vqtouch.plugins.generator.vq_diffusion import VQDiffusionConfig


def _pair(kernel: int) -> tuple[DiffusionTransformer, DiffusionTransformer]:
    torch.manual_seed(0)
    plain = DiffusionTransformer(16, 10, (4, 6), 8, depth=2, width=16, heads=2)
    torch.manual_seed(0)
    with_conv = DiffusionTransformer(16, 10, (4, 6), 8, depth=2, width=16, heads=2, mlp_conv=kernel)
    return plain, with_conv


def test_the_convolution_starts_as_the_plain_mlp_and_old_weights_load_into_it():
    plain, with_conv = _pair(3)
    missing, unexpected = with_conv.load_state_dict(plain.state_dict(), strict=False)
    assert not unexpected and missing and all(".mlp_conv." in key for key in missing)
    codes = torch.randint(0, 17, (3, 24))
    t_B = torch.tensor([0, 4, 9])
    condition = torch.randn(3, 2, 8)
    assert torch.equal(plain(codes, t_B, condition), with_conv(codes, t_B, condition))


@pytest.mark.parametrize("kernel", [3, 5])
def test_the_convolution_mixes_only_a_cell_and_its_grid_neighbours(kernel):
    """Changing one code cell's input changes the MLP's output only within kernel // 2 rows and
    columns of it on the (4, 6) grid: the sequence is laid back on the grid row-major."""
    _, model = _pair(kernel)
    block = model.blocks[0]
    torch.manual_seed(1)
    for parameter in block.mlp_conv.parameters():
        parameter.data.normal_()
    h_BLd = torch.randn(1, 24, 16)
    row, col = 2, 1
    changed = h_BLd.clone()
    changed[0, row * 6 + col] += 1.0
    moved_HW = (block._mlp(changed) - block._mlp(h_BLd)).abs().amax(-1).view(4, 6) > 1e-6
    rows, cols = torch.meshgrid(torch.arange(4), torch.arange(6), indexing="ij")
    reach = kernel // 2
    expected_HW = ((rows - row).abs() <= reach) & ((cols - col).abs() <= reach)
    assert torch.equal(moved_HW, expected_HW)


@pytest.mark.parametrize("kernel", [2, 4, -1])
def test_an_even_or_negative_kernel_is_refused_with_the_fix(kernel):
    with pytest.raises(ValidationError, match="mlp_conv"):
        VQDiffusionConfig(mlp_conv=kernel)
    with pytest.raises(ValueError, match="odd kernel size"):
        DiffusionTransformer(16, 10, (4, 4), 8, depth=1, width=16, heads=2, mlp_conv=kernel)

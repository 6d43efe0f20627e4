"""Deformable convolution (DCNv1 / DCNv2) for the DM-VQGAN ResNet blocks.

Three interchangeable implementations of ``torchvision.ops.deform_conv2d``'s maths:

* :func:`deform_conv2d_grid_sample`: pure PyTorch, one ``F.grid_sample`` that gathers all
  k*k deformed taps of every output pixel, then one matmul with the flattened weight (an
  im2col convolution whose "im2col" is bilinear).  Autograd, every device and every dtype
  come for free, and on CPU it is faster than torchvision's kernel (see
  ``bench/bench_deformable.py``).
* :func:`deform_conv2d_gather`: pure PyTorch, channels last: the four bilinear corners of every
  tap are one fused gather-and-weighted-sum (``F.embedding_bag`` with per-sample weights, whose
  forward and backward are single kernels), laid out so the result is already the im2col
  matrix, then one matmul.
* :func:`deform_conv2d_torchvision`: a thin wrapper around ``torchvision.ops.deform_conv2d``,
  kept as the reference and as an option.  torchvision is imported inside the function:
  ``import torchvision`` imports ``torchvision.models``, which importing vqtouch must not do.

Both follow torchvision's conventions exactly:

* ``offset`` is ``[B, 2*G*kh*kw, Ho, Wo]``; for offset group g and kernel point
  k = i*kw + j, channel ``g*2*kh*kw + 2k`` is the row shift dy and ``+1`` the column shift dx;
* tap k of output pixel (y_o, x_o) samples ``y = y_o*stride - pad + i*dilation + dy`` and
  ``x = x_o*stride - pad + j*dilation + dx``, bilinearly, reading zeros outside the image;
* ``mask`` (DCNv2 modulation, optional) is ``[B, G*kh*kw, Ho, Wo]`` and scales each sampled tap.

:class:`DeformableConv2d` is the drop-in layer for a kxk ``nn.Conv2d``: it predicts bounded
offsets (and a mask) from its input with a zero-initialised convolution, so a freshly built
layer computes exactly the plain convolution.
"""

from __future__ import annotations

import importlib.util
import math
from typing import Literal

import torch
import torch.nn.functional as F
from torch import nn

from vqtouch.core import ConfigError

from .deformable_geometry import (
    IntPair,
    _checked_geometry,
    _pair,
    _result_dtype,
    _sample_dtype,
    _tap_positions,
)

__all__ = [
    "DeformableConv2d",
    "bilinear_taps",
    "deform_conv2d_gather",
    "deform_conv2d_grid_sample",
    "deform_conv2d_torchvision",
]

Backend = Literal["grid_sample", "gather", "torchvision"]
BACKENDS: tuple[str, ...] = ("grid_sample", "gather", "torchvision")


def deform_conv2d_grid_sample(
    input: torch.Tensor,
    offset: torch.Tensor,
    weight: torch.Tensor,
    bias: torch.Tensor | None = None,
    stride: IntPair = 1,
    padding: IntPair = 0,
    dilation: IntPair = 1,
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """Deformable convolution with ``torchvision.ops.deform_conv2d``'s semantics, in pure PyTorch.

    Args:
        input: ``[B, C_in, H, W]``.
        offset: ``[B, 2*G*kh*kw, Ho, Wo]`` (dy, dx) per offset group and kernel point, in pixels.
        weight: ``[C_out, C_in/groups, kh, kw]`` (weight groups are inferred as in torchvision).
        bias: ``[C_out]`` or None.
        stride, padding, dilation: ints or (h, w) pairs.
        mask: ``[B, G*kh*kw, Ho, Wo]`` modulation (DCNv2) or None (DCNv1).

    Returns:
        ``[B, C_out, Ho, Wo]`` in the input's dtype, or the autocast dtype under autocast.

    All K = kh*kw taps of all output pixels are gathered by a single ``F.grid_sample`` over a
    grid of ``[B*G, K*Ho, Wo, 2]`` points (kernel-point-major: the sampled tensor then *is* the
    im2col matrix ``[B, C_in*K, Ho*Wo]``, with no permute copy), followed by one matmul with
    the weight seen as ``[C_out, C_in*K]``.  That matrix is ``C_in*K*Ho*Wo`` values per image,
    the size of torchvision's column buffer; for backward autograd keeps it twice (before the
    mask, for the mask gradient, and after, for the weight gradient) plus the grid.

    Dtypes: sample positions reach tens to hundreds of pixels and need sub-pixel precision,
    which bfloat16 (8 mantissa bits) cannot give, so the grid, the bilinear sampling and the
    mask product run in float32 (float64 for float64 inputs, which keeps ``gradcheck``
    exact), with autocast off; the matmul then runs in the result dtype (autocast's
    bfloat16/float16 when autocast is on, the input dtype otherwise), like ``F.conv2d``.
    """
    stride_hw, padding_hw, dilation_hw, offset_groups, weight_groups, out_h, out_w = _checked_geometry(
        input, offset, weight, bias, stride, padding, dilation, mask
    )
    result_dtype, sample_dtype, device = _result_dtype(input), _sample_dtype(input), input.device
    kernel_hw = (weight.shape[2], weight.shape[3])
    with torch.autocast(device_type=device.type, enabled=False):
        grid_N_KHo_Wo_2 = _sampling_grid(
            offset, input.shape[2:], (out_h, out_w), kernel_hw, stride_hw, padding_hw, dilation_hw, sample_dtype, device
        )
        sampled = _grid_sample_taps(input, grid_N_KHo_Wo_2, mask, offset_groups, kernel_hw, sample_dtype)
    return _im2col_matmul(input, sampled, weight, bias, weight_groups, out_h, out_w, result_dtype)


def _sampling_grid(
    offset: torch.Tensor,
    size_hw: tuple[int, int],
    out_hw: tuple[int, int],
    kernel_hw: tuple[int, int],
    stride_hw: tuple[int, int],
    padding_hw: tuple[int, int],
    dilation_hw: tuple[int, int],
    sample_dtype: torch.dtype,
    device: torch.device,
) -> torch.Tensor:
    """The deformed tap positions of every output pixel as a ``grid_sample`` grid
    ``[B*G, K*Ho, Wo, 2]`` (kernel-point-major) over an input of ``size_hw``."""
    (height, width), (out_h, out_w), (kernel_h, kernel_w) = size_hw, out_hw, kernel_hw
    taps = kernel_h * kernel_w
    batch, offset_groups = offset.shape[0], offset.shape[1] // (2 * taps)
    rows_o, cols_o, tap_rows_K, tap_cols_K = _tap_positions(
        out_h, out_w, kernel_h, kernel_w, stride_hw, padding_hw, dilation_hw, sample_dtype, device
    )
    base_y_KHW = (tap_rows_K[:, None, None] + rows_o[None, :, None]).expand(taps, out_h, out_w)
    base_x_KHW = (tap_cols_K[:, None, None] + cols_o[None, None, :]).expand(taps, out_h, out_w)

    offset_BGK2HW = offset.to(sample_dtype).reshape(batch, offset_groups, taps, 2, out_h, out_w)
    y_BGKHW = base_y_KHW + offset_BGK2HW[:, :, :, 0]
    x_BGKHW = base_x_KHW + offset_BGK2HW[:, :, :, 1]
    # Pixel index -> grid_sample's [-1, 1] with align_corners=False (pixel i is centred at
    # (2i + 1)/size - 1).  Unlike align_corners=True's 2i/(size - 1) - 1 this stays finite for
    # 1-pixel-wide inputs; padding_mode="zeros" gives torchvision's zero-outside bilinear.
    grid_BGKHW2 = torch.stack(((2 * x_BGKHW + 1) / width - 1, (2 * y_BGKHW + 1) / height - 1), dim=-1)
    return grid_BGKHW2.reshape(batch * offset_groups, taps * out_h, out_w, 2)


def _grid_sample_taps(
    input: torch.Tensor,
    grid_N_KHo_Wo_2: torch.Tensor,
    mask: torch.Tensor | None,
    offset_groups: int,
    kernel_hw: tuple[int, int],
    sample_dtype: torch.dtype,
) -> torch.Tensor:
    """The input sampled bilinearly (zeros outside) at the grid's positions, scaled by the mask when
    there is one: ``[B*G, C_in/G, K*Ho, Wo]``, or its ``[B, G, C_in/G, K, Ho, Wo]`` view with a mask."""
    batch, in_channels, height, width = input.shape
    taps = kernel_hw[0] * kernel_hw[1]
    out_h, out_w = grid_N_KHo_Wo_2.shape[1] // taps, grid_N_KHo_Wo_2.shape[2]
    input_N_Cg_H_W = input.to(sample_dtype).reshape(batch * offset_groups, in_channels // offset_groups, height, width)
    sampled = F.grid_sample(
        input_N_Cg_H_W, grid_N_KHo_Wo_2, mode="bilinear", padding_mode="zeros", align_corners=False
    )  # [B*G, C_in/G, K*Ho, Wo]
    if mask is not None:
        sampled_BGCKHW = sampled.view(batch, offset_groups, in_channels // offset_groups, taps, out_h, out_w)
        mask_BG1KHW = mask.to(sample_dtype).reshape(batch, offset_groups, 1, taps, out_h, out_w)
        sampled = sampled_BGCKHW * mask_BG1KHW
    return sampled


def _im2col_matmul(
    input: torch.Tensor,
    sampled: torch.Tensor,
    weight: torch.Tensor,
    bias: torch.Tensor | None,
    weight_groups: int,
    out_h: int,
    out_w: int,
    result_dtype: torch.dtype,
) -> torch.Tensor:
    """The sampled taps (the im2col matrix, channel-major) times the weight, plus the bias:
    ``[B, C_out, Ho, Wo]`` in ``result_dtype``."""
    batch, in_channels = input.shape[:2]
    out_channels, _, kernel_h, kernel_w = weight.shape
    taps = kernel_h * kernel_w
    # Column index c*K + k matches weight.reshape(C_out, C_in*K): this is im2col.
    in_per_group = in_channels // weight_groups
    columns_B_Gw_CK_L = sampled.reshape(batch, weight_groups, in_per_group * taps, out_h * out_w)
    weight_Gw_O_CK = weight.reshape(weight_groups, out_channels // weight_groups, in_per_group * taps)
    if not torch.is_autocast_enabled(input.device.type):
        # Outside autocast the matmul runs in the input's dtype, as F.conv2d would (a weight of
        # another dtype is an error there too); under autocast, matmul casts both operands itself.
        columns_B_Gw_CK_L = columns_B_Gw_CK_L.to(input.dtype)
    out_B_Gw_O_L = torch.matmul(weight_Gw_O_CK, columns_B_Gw_CK_L)
    out_BOHW = out_B_Gw_O_L.reshape(batch, out_channels, out_h, out_w)
    if bias is not None:
        out_BOHW = out_BOHW + bias.to(out_BOHW.dtype).view(1, out_channels, 1, 1)
    return out_BOHW.to(result_dtype)


class _RowGradient(torch.autograd.Function):
    """Identity on the gathered taps whose backward gives the gradient of the gathered rows.

    ``F.embedding_bag``'s own backward for its table (the "dense" one) sorts the indices and
    accumulates with a generic kernel: profiled on the CPU it cost 1.5-2x the forward gather.
    Here the gradient of the rows is the transposed gather, computed as another ``embedding_bag``:
    the corner entries sorted by the row they read (one argsort) are the bags, each row's
    gradient the factor-weighted sum of the taps that read it, with rows nobody read left 0."""

    @staticmethod
    def forward(
        ctx, sampled_MC: torch.Tensor, rows_RC: torch.Tensor, index_M4: torch.Tensor, factor_M4: torch.Tensor
    ) -> torch.Tensor:
        ctx.save_for_backward(index_M4, factor_M4)
        ctx.num_rows = rows_RC.shape[0]
        return sampled_MC.view_as(sampled_MC)

    @staticmethod
    def backward(ctx, grad_MC: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None, None, None]:
        grad_rows_RC = None
        if ctx.needs_input_grad[1]:
            index_M4, factor_M4 = ctx.saved_tensors
            flat = index_M4.reshape(-1)
            order = torch.argsort(flat)
            counts = torch.bincount(flat, minlength=ctx.num_rows)
            starts = counts.cumsum(0) - counts  # bag r: the corner entries that read row r
            corners = index_M4.shape[1]
            grad_rows_RC = F.embedding_bag(
                order // corners,
                grad_MC.contiguous(),
                starts,
                mode="sum",
                per_sample_weights=factor_M4.reshape(-1)[order],
            )
        return grad_MC, grad_rows_RC, None, None


def bilinear_taps(rows_RC: torch.Tensor, index_M4: torch.Tensor, factor_M4: torch.Tensor) -> torch.Tensor:
    """``sampled[m] = sum_j factor[m, j] * rows[index[m, j]]``: (M, C) from the table (R, C), the
    corner indices (M, 4) and their factors (M, 4), differentiable in ``rows`` and ``factor``.

    The forward and the factors' gradient are ``F.embedding_bag``'s own fused kernels (each tap a
    bag of its four corner rows, the factors its per-sample weights); the rows' gradient is
    :class:`_RowGradient`'s transposed gather.  Done with separate gather, multiply and sum ops
    the same maths ran 2-4x slower than ``grid_sample`` on CPU."""
    sampled_MC = F.embedding_bag(index_M4, rows_RC.detach(), mode="sum", per_sample_weights=factor_M4)
    return _RowGradient.apply(sampled_MC, rows_RC, index_M4, factor_M4.detach())


def deform_conv2d_gather(
    input: torch.Tensor,
    offset: torch.Tensor,
    weight: torch.Tensor,
    bias: torch.Tensor | None = None,
    stride: IntPair = 1,
    padding: IntPair = 0,
    dilation: IntPair = 1,
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """Deformable convolution with :func:`deform_conv2d_grid_sample`'s signature, semantics and
    dtype rules, computed as a channels-last bilinear gather and one matmul.

    The input is laid out as rows of channels (``[B*G*H*W, C_in/G]``, channels last).  The four
    bilinear corners of every tap of every output pixel are fetched by one row gather, ordered
    (image, output pixel, tap), so that their weighted sum is already the im2col matrix
    ``[B*Ho*Wo, K*C_in]`` with no permute copy.  Each corner's bilinear weight, its in-image test
    (zeros outside, as torchvision) and the DCNv2 mask are folded into one per-corner factor, and
    :func:`bilinear_taps` gathers and sums them (one fused kernel each way).  One matmul with the
    weight seen as ``[K*C_in, C_out]`` finishes.  Dtypes as :func:`deform_conv2d_grid_sample`.
    """
    stride_hw, padding_hw, dilation_hw, offset_groups, weight_groups, out_h, out_w = _checked_geometry(
        input, offset, weight, bias, stride, padding, dilation, mask
    )
    batch, in_channels, height, width = input.shape
    kernel_h, kernel_w = weight.shape[2:]
    taps, pixels = kernel_h * kernel_w, out_h * out_w
    group_channels = in_channels // offset_groups
    images = batch * offset_groups
    result_dtype, sample_dtype, device = _result_dtype(input), _sample_dtype(input), input.device

    with torch.autocast(device_type=device.type, enabled=False):
        rows_o, cols_o, tap_rows_K, tap_cols_K = _tap_positions(
            out_h, out_w, kernel_h, kernel_w, stride_hw, padding_hw, dilation_hw, sample_dtype, device
        )
        # Positions ordered (image, output row, output column, tap): pixel-major, tap-minor.
        base_y_HWK = (rows_o[:, None, None] + tap_rows_K).expand(out_h, out_w, taps)
        base_x_HWK = (cols_o[None, :, None] + tap_cols_K).expand(out_h, out_w, taps)
        # Made contiguous in that order once (it is small), so every tensor derived from it is too.
        offset_NHWK2 = offset.to(sample_dtype).reshape(images, taps, 2, out_h, out_w).permute(0, 3, 4, 1, 2)
        offset_NHWK2 = offset_NHWK2.contiguous()
        y_NHWK1 = (base_y_HWK + offset_NHWK2[..., 0])[..., None]
        x_NHWK1 = (base_x_HWK + offset_NHWK2[..., 1])[..., None]
        index, factor = _corner_rows_and_factors(y_NHWK1, x_NHWK1, mask, (height, width), sample_dtype)
        rows = input.to(sample_dtype).reshape(images, group_channels, height * width).transpose(1, 2)
        rows = rows.reshape(images * height * width, group_channels)
        sampled = bilinear_taps(rows, index.reshape(-1, 4), factor.reshape(-1, 4))  # [N*Ho*Wo*K, C/G]
        if offset_groups > 1:  # channel c = g*C/G + c' must sit next to its tap: [B, L, K, C]
            sampled = sampled.view(batch, offset_groups, pixels, taps, group_channels).permute(0, 2, 3, 1, 4)
        columns = sampled.reshape(batch * pixels, taps, in_channels)
    return _channels_last_matmul(input, columns, weight, bias, weight_groups, out_h, out_w, result_dtype)


def _corner_rows_and_factors(
    y_NHWK1: torch.Tensor,
    x_NHWK1: torch.Tensor,
    mask: torch.Tensor | None,
    size_hw: tuple[int, int],
    sample_dtype: torch.dtype,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The rows (in the ``[N*H*W, C/G]`` table of an input of ``size_hw``) of the four bilinear
    corners of every tap at positions ``[N, Ho, Wo, K, 1]``, and each corner's factor: its bilinear
    weight, zero outside the image, times the mask when there is one.  Both ``[N, Ho, Wo, K, 4]``."""
    height, width = size_hw
    images, out_h, out_w, taps = y_NHWK1.shape[:4]
    device = y_NHWK1.device
    # The corners' indices carry no gradient; the fractions do (through the offsets).  Corners
    # last, so that each tap's four are one contiguous bag: [N, Ho, Wo, K, 4].
    y0, x0 = y_NHWK1.detach().floor(), x_NHWK1.detach().floor()
    fy, fx = y_NHWK1 - y0, x_NHWK1 - x0
    corner = torch.tensor([0.0, 1.0], dtype=sample_dtype, device=device)
    corner_y = y0 + corner.repeat_interleave(2)  # corners (y0, x0), (y0, x0+1), (y0+1, x0), (y0+1, x0+1)
    corner_x = x0 + corner.repeat(2)
    factor = torch.cat(((1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx), dim=-1)
    inside = (corner_y >= 0) & (corner_y <= height - 1) & (corner_x >= 0) & (corner_x <= width - 1)
    factor = factor * inside
    if mask is not None:
        mask_NHWK1 = mask.to(sample_dtype).reshape(images, taps, out_h, out_w).permute(0, 2, 3, 1)[..., None]
        factor = factor * mask_NHWK1
    image_start = (torch.arange(images, device=device) * (height * width)).view(images, 1, 1, 1, 1)
    # A NaN position (NaN weights) must give NaN, as grid_sample does, not an out-of-range index:
    # its factor is already NaN, so any in-range row will do.
    index = (
        corner_y.nan_to_num(0).clamp(0, height - 1) * width + corner_x.nan_to_num(0).clamp(0, width - 1)
    ).long() + image_start
    return index, factor


def _channels_last_matmul(
    input: torch.Tensor,
    columns: torch.Tensor,
    weight: torch.Tensor,
    bias: torch.Tensor | None,
    weight_groups: int,
    out_h: int,
    out_w: int,
    result_dtype: torch.dtype,
) -> torch.Tensor:
    """The im2col matrix ``[B*Ho*Wo, K, C_in]`` (tap-major) times the weight, plus the bias:
    ``[B, C_out, Ho, Wo]`` in ``result_dtype``."""
    batch, in_channels = input.shape[:2]
    out_channels, _, kernel_h, kernel_w = weight.shape
    taps, pixels = kernel_h * kernel_w, out_h * out_w
    in_per_group, out_per_group = in_channels // weight_groups, out_channels // weight_groups
    weight_GwKCO = weight.reshape(weight_groups, out_per_group, in_per_group, taps).permute(0, 3, 2, 1)
    if not torch.is_autocast_enabled(input.device.type):
        columns = columns.to(input.dtype)  # as F.conv2d: the matmul in the input's dtype
    else:
        columns, weight_GwKCO = columns.to(result_dtype), weight_GwKCO.to(result_dtype)
    if weight_groups == 1:
        out_LO = columns.reshape(batch * pixels, taps * in_channels) @ weight_GwKCO.reshape(
            taps * in_channels, out_channels
        )
    else:
        grouped = columns.view(batch * pixels, taps, weight_groups, in_per_group)
        out_LO = torch.einsum("lkgc,gkco->lgo", grouped, weight_GwKCO).reshape(batch * pixels, out_channels)
    out_BOHW = out_LO.view(batch, out_h, out_w, out_channels).permute(0, 3, 1, 2)
    if bias is not None:
        out_BOHW = out_BOHW + bias.to(out_BOHW.dtype).view(1, out_channels, 1, 1)
    return out_BOHW.contiguous().to(result_dtype)


def deform_conv2d_torchvision(
    input: torch.Tensor,
    offset: torch.Tensor,
    weight: torch.Tensor,
    bias: torch.Tensor | None = None,
    stride: IntPair = 1,
    padding: IntPair = 0,
    dilation: IntPair = 1,
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """``torchvision.ops.deform_conv2d`` with the same signature, dtype rules and checks as
    :func:`deform_conv2d_grid_sample`.

    torchvision is imported here, on first use, never at module import (``import torchvision``
    pulls in ``torchvision.models``).  Its CPU kernel has no bfloat16 (float, double and half
    only), so reduced-precision inputs are computed in float32 with autocast off and the
    result is cast back to the input's dtype, or to the autocast dtype under autocast.
    """
    from torchvision.ops import deform_conv2d as torchvision_deform_conv2d

    stride_hw, padding_hw, dilation_hw, *_ = _checked_geometry(
        input, offset, weight, bias, stride, padding, dilation, mask
    )
    result_dtype, compute_dtype = _result_dtype(input), _sample_dtype(input)
    with torch.autocast(device_type=input.device.type, enabled=False):
        out_BOHW = torchvision_deform_conv2d(
            input.to(compute_dtype),
            offset.to(compute_dtype),
            weight.to(compute_dtype),
            None if bias is None else bias.to(compute_dtype),
            stride=stride_hw,
            padding=padding_hw,
            dilation=dilation_hw,
            mask=None if mask is None else mask.to(compute_dtype),
        )
    return out_BOHW.to(result_dtype)


_BACKEND_FUNCTIONS = {
    "grid_sample": deform_conv2d_grid_sample,
    "gather": deform_conv2d_gather,
    "torchvision": deform_conv2d_torchvision,
}


class DeformableConv2d(nn.Module):
    """Drop-in deformable replacement for a kxk ``nn.Conv2d`` (DCNv2 by default, DCNv1 without modulation).

    A plain convolution with the same kernel, stride, padding and dilation (``offset_conv``)
    predicts, from the layer's input, ``2*G*k*k`` raw offsets and, with ``modulation``,
    ``G*k*k`` raw mask logits.  Then:

    * offset = ``max_offset * tanh(raw)`` pixels.  Unbounded offsets explode early in training
      (a large step sends taps far outside the feature map, where they read zeros and get no
      useful gradient, and the offset magnitude keeps growing; BasicSR warns above 50 px).
      The bound keeps every tap within ``max_offset`` pixels of its regular position.
      At init tanh'(0) = 1, so the effective offset learning rate is ``max_offset`` times the
      branch's; consider a reduced learning rate for :meth:`offset_parameters` (mmengine uses x0.1).
    * mask = ``2 * sigmoid(raw)`` in (0, 2).  The factor 2 makes the zero-initialised mask
      exactly 1 instead of sigmoid(0) = 0.5, so that the layer starts as the plain convolution
      rather than half of it (which would halve the residual branch it is dropped into).

    ``offset_conv`` is zero-initialised (weight and bias): at init offsets are 0 and the mask
    is 1, so the layer equals ``F.conv2d(x, self.weight, self.bias, ...)`` exactly, with
    either value of ``modulation``.  ``weight``/``bias`` are initialised like ``nn.Conv2d``'s.

    Args:
        in_channels, out_channels, kernel_size, stride, padding, dilation, bias: as ``nn.Conv2d``.
        groups: number of *offset* groups G (channels split into G groups, each with its own
            offsets and mask); the convolution weight itself is always dense.
        modulation: learn a DCNv2 mask (False: DCNv1).
        max_offset: bound on each offset component, in pixels of the input.
        backend: ``"gather"`` (pure PyTorch, channels last; the default, fastest on CPU in
            ``bench/bench_dm_vqgan.py``), ``"grid_sample"`` (pure PyTorch) or ``"torchvision"``.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel_size: IntPair = 3,
        stride: IntPair = 1,
        padding: IntPair = 1,
        dilation: IntPair = 1,
        groups: int = 1,
        bias: bool = True,
        modulation: bool = True,
        max_offset: float = 4.0,
        backend: Backend = "gather",
    ) -> None:
        super().__init__()
        if in_channels < 1 or out_channels < 1:
            raise ValueError(
                f"DeformableConv2d: channel counts must be positive, got in {in_channels}, out {out_channels}"
            )
        if groups < 1 or in_channels % groups:
            raise ValueError(
                f"DeformableConv2d: groups (offset groups) must divide in_channels={in_channels}, got {groups}"
            )
        if not (isinstance(max_offset, (int, float)) and math.isfinite(max_offset) and max_offset > 0):
            raise ValueError(
                f"DeformableConv2d: max_offset must be a positive finite number of pixels, got {max_offset!r}"
            )
        if backend not in BACKENDS:
            raise ValueError(f"DeformableConv2d: backend must be one of {BACKENDS}, got {backend!r}")
        if backend == "torchvision" and importlib.util.find_spec("torchvision") is None:
            # Fail when the model is built, not at its first forward pass deep inside training.
            raise ConfigError(
                "deformable_backend 'torchvision' needs torchvision, which is not installed: "
                "pip install torchvision (it comes with vqtouch[clip]), or use the default "
                "'gather' backend (same maths, no extra package)"
            )
        self.in_channels, self.out_channels = in_channels, out_channels
        self.kernel_size = _pair(kernel_size, "kernel_size")
        self.stride, self.padding = _pair(stride, "stride"), _pair(padding, "padding")
        self.dilation = _pair(dilation, "dilation")
        if min(self.kernel_size) < 1 or min(self.stride) < 1 or min(self.dilation) < 1 or min(self.padding) < 0:
            raise ValueError(
                f"DeformableConv2d: need kernel_size, stride, dilation >= 1 and padding >= 0; got "
                f"kernel_size {self.kernel_size}, stride {self.stride}, dilation {self.dilation}, "
                f"padding {self.padding}"
            )
        self.groups, self.modulation = groups, modulation
        self.max_offset, self.backend = float(max_offset), backend
        taps = self.kernel_size[0] * self.kernel_size[1]
        self.offset_channels = 2 * groups * taps
        self.mask_channels = groups * taps if modulation else 0

        self.weight = nn.Parameter(torch.empty(out_channels, in_channels, *self.kernel_size))
        self.bias = nn.Parameter(torch.empty(out_channels)) if bias else None
        self.offset_conv = nn.Conv2d(
            in_channels,
            self.offset_channels + self.mask_channels,
            self.kernel_size,
            stride=self.stride,
            padding=self.padding,
            dilation=self.dilation,
            bias=True,
        )
        # Detached scalar tensor; turned into a float only when asked, to avoid a device sync per step.
        self._last_mean_abs_offset: torch.Tensor | None = None
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """``nn.Conv2d``'s initialisation for the main weight/bias; zeros for the offset/mask branch."""
        nn.init.kaiming_uniform_(self.weight, a=math.sqrt(5))
        if self.bias is not None:
            fan_in = self.weight.shape[1] * self.kernel_size[0] * self.kernel_size[1]
            bound = 1 / math.sqrt(fan_in)
            nn.init.uniform_(self.bias, -bound, bound)
        nn.init.zeros_(self.offset_conv.weight)
        nn.init.zeros_(self.offset_conv.bias)

    def offset_parameters(self) -> list[nn.Parameter]:
        """Parameters of the offset/mask branch (for a separate, usually lower, learning rate)."""
        return list(self.offset_conv.parameters())

    def offsets_and_mask(self, x_BCHW: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Bounded offsets ``[B, 2*G*K, Ho, Wo]`` and mask ``[B, G*K, Ho, Wo]`` (None without modulation).

        The branch runs in its parameters' dtype (float32 normally) with autocast off: the
        offsets are amplified by ``max_offset`` and set sample positions, and in bfloat16 they
        were off by up to 0.085 px at |offset| ~ 4, giving ~3% relative output error against
        0.3% for a plain bfloat16 convolution.  The branch has only 3*G*k*k output channels
        (27 for 3x3, against 64-256 for the main convolution), so float32 here is cheap.
        """
        with torch.autocast(device_type=x_BCHW.device.type, enabled=False):
            raw = self.offset_conv(x_BCHW.to(self.offset_conv.weight.dtype))
            raw = raw.to(torch.promote_types(raw.dtype, torch.float32))
            offset_B2KHW = self.max_offset * torch.tanh(raw[:, : self.offset_channels])
            mask_BKHW = 2.0 * torch.sigmoid(raw[:, self.offset_channels :]) if self.modulation else None
        return offset_B2KHW, mask_BKHW

    def forward(self, x_BCHW: torch.Tensor) -> torch.Tensor:
        """Deformable convolution of ``x_BCHW`` ``[B, in_channels, H, W]`` -> ``[B, out_channels, Ho, Wo]``."""
        if x_BCHW.dim() != 4:
            raise ValueError(f"DeformableConv2d: expected a 4-D input [B, C, H, W], got shape {tuple(x_BCHW.shape)}")
        if x_BCHW.shape[1] != self.in_channels:
            raise ValueError(
                f"DeformableConv2d: expected {self.in_channels} input channels, got {x_BCHW.shape[1]} "
                f"(input shape {tuple(x_BCHW.shape)})"
            )
        out_h = (
            x_BCHW.shape[2] + 2 * self.padding[0] - self.dilation[0] * (self.kernel_size[0] - 1) - 1
        ) // self.stride[0] + 1
        out_w = (
            x_BCHW.shape[3] + 2 * self.padding[1] - self.dilation[1] * (self.kernel_size[1] - 1) - 1
        ) // self.stride[1] + 1
        if out_h < 1 or out_w < 1:
            raise ValueError(
                f"DeformableConv2d: input {tuple(x_BCHW.shape[2:])} is too small for kernel "
                f"{self.kernel_size} with padding {self.padding} and dilation {self.dilation}"
            )
        offset_B2KHW, mask_BKHW = self.offsets_and_mask(x_BCHW)
        with torch.no_grad():
            self._last_mean_abs_offset = offset_B2KHW.detach().abs().mean()
        return _BACKEND_FUNCTIONS[self.backend](
            x_BCHW,
            offset_B2KHW,
            self.weight,
            self.bias,
            stride=self.stride,
            padding=self.padding,
            dilation=self.dilation,
            mask=mask_BKHW,
        )

    @property
    def last_mean_abs_offset(self) -> float | None:
        """Mean |offset| in pixels over the last forward's offsets (None before any forward), for logging."""
        if self._last_mean_abs_offset is None:
            return None
        return float(self._last_mean_abs_offset)

    def extra_repr(self) -> str:
        """Constructor arguments, like ``nn.Conv2d``'s repr."""
        return (
            f"{self.in_channels}, {self.out_channels}, kernel_size={self.kernel_size}, stride={self.stride}, "
            f"padding={self.padding}, dilation={self.dilation}, groups={self.groups}, "
            f"bias={self.bias is not None}, modulation={self.modulation}, max_offset={self.max_offset}, "
            f"backend={self.backend!r}"
        )

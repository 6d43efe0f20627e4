"""Argument checks, output geometry, dtypes and undeformed tap positions shared by the deformable
convolution backends of :mod:`.deformable`."""

from __future__ import annotations

import torch

IntPair = int | tuple[int, int]


def _pair(value: IntPair, name: str) -> tuple[int, int]:
    """``value`` as a (height, width) pair of ints."""
    if isinstance(value, int):
        return value, value
    if isinstance(value, (tuple, list)) and len(value) == 2 and all(isinstance(v, int) for v in value):
        return int(value[0]), int(value[1])
    raise ValueError(f"{name} must be an int or a pair of ints, got {value!r}")


def _check_shapes(
    input: torch.Tensor,
    offset: torch.Tensor,
    weight: torch.Tensor,
    bias: torch.Tensor | None,
    stride: tuple[int, int],
    padding: tuple[int, int],
    dilation: tuple[int, int],
    mask: torch.Tensor | None,
) -> tuple[int, int, int, int]:
    """Validate a deform_conv2d call; return (offset_groups, weight_groups, out_height, out_width)."""
    if input.dim() != 4:
        raise ValueError(f"deform_conv2d: input must be [B, C, H, W], got shape {tuple(input.shape)}")
    if weight.dim() != 4:
        raise ValueError(f"deform_conv2d: weight must be [C_out, C_in/groups, kh, kw], got shape {tuple(weight.shape)}")
    if offset.dim() != 4:
        raise ValueError(f"deform_conv2d: offset must be [B, 2*G*kh*kw, Ho, Wo], got shape {tuple(offset.shape)}")
    if min(stride) < 1 or min(dilation) < 1 or min(padding) < 0:
        raise ValueError(
            f"deform_conv2d: need stride >= 1, dilation >= 1, padding >= 0; got stride {stride}, "
            f"dilation {dilation}, padding {padding}"
        )
    batch, in_channels, height, width = input.shape
    out_channels, in_per_weight_group, kernel_h, kernel_w = weight.shape
    taps = kernel_h * kernel_w
    if in_per_weight_group == 0 or in_channels % in_per_weight_group:
        raise ValueError(
            f"deform_conv2d: input has {in_channels} channels, not a multiple of the weight's "
            f"{in_per_weight_group} input channels per group (weight shape {tuple(weight.shape)})"
        )
    weight_groups = in_channels // in_per_weight_group
    if out_channels % weight_groups:
        raise ValueError(
            f"deform_conv2d: {out_channels} output channels are not divisible into {weight_groups} weight groups"
        )
    out_h = (height + 2 * padding[0] - dilation[0] * (kernel_h - 1) - 1) // stride[0] + 1
    out_w = (width + 2 * padding[1] - dilation[1] * (kernel_w - 1) - 1) // stride[1] + 1
    if out_h < 1 or out_w < 1:
        raise ValueError(
            f"deform_conv2d: input {height}x{width} is too small for a {kernel_h}x{kernel_w} kernel with "
            f"padding {padding}, dilation {dilation} (output would be {out_h}x{out_w})"
        )
    if offset.shape[0] != batch or offset.shape[1] % (2 * taps) or offset.shape[1] == 0:
        raise ValueError(
            f"deform_conv2d: offset must be [B={batch}, 2*G*{taps}, {out_h}, {out_w}] for this input and "
            f"kernel, got shape {tuple(offset.shape)}"
        )
    offset_groups = offset.shape[1] // (2 * taps)
    if tuple(offset.shape[2:]) != (out_h, out_w):
        raise ValueError(
            f"deform_conv2d: offset spatial size {tuple(offset.shape[2:])} differs from the output size "
            f"{(out_h, out_w)} given by the input, kernel, stride, padding and dilation"
        )
    if in_channels % offset_groups:
        raise ValueError(
            f"deform_conv2d: input channels {in_channels} are not divisible into {offset_groups} offset "
            f"groups (offset has {offset.shape[1]} channels)"
        )
    if mask is not None and tuple(mask.shape) != (batch, offset_groups * taps, out_h, out_w):
        raise ValueError(
            f"deform_conv2d: mask must be [B, G*kh*kw, Ho, Wo] = "
            f"{[batch, offset_groups * taps, out_h, out_w]}, got shape {tuple(mask.shape)}"
        )
    if bias is not None and tuple(bias.shape) != (out_channels,):
        raise ValueError(f"deform_conv2d: bias must be [{out_channels}], got shape {tuple(bias.shape)}")
    return offset_groups, weight_groups, out_h, out_w


def _result_dtype(input: torch.Tensor) -> torch.dtype:
    """Dtype a convolution would return here: the autocast dtype if autocast is on, else the input's."""
    device_type = input.device.type
    if torch.is_autocast_enabled(device_type):
        return torch.get_autocast_dtype(device_type)
    return input.dtype


def _checked_geometry(
    input: torch.Tensor,
    offset: torch.Tensor,
    weight: torch.Tensor,
    bias: torch.Tensor | None,
    stride: IntPair,
    padding: IntPair,
    dilation: IntPair,
    mask: torch.Tensor | None,
) -> tuple:
    """The (h, w) pairs of stride, padding and dilation, then the offset groups, weight groups and
    output size of a checked deformable-convolution call (see :func:`_check_shapes`)."""
    stride_hw, padding_hw = _pair(stride, "stride"), _pair(padding, "padding")
    dilation_hw = _pair(dilation, "dilation")
    return (
        stride_hw,
        padding_hw,
        dilation_hw,
        *_check_shapes(input, offset, weight, bias, stride_hw, padding_hw, dilation_hw, mask),
    )


def _sample_dtype(input: torch.Tensor) -> torch.dtype:
    """Where sample positions and bilinear weights are computed: float64 for float64 inputs (exact
    gradcheck), float32 otherwise (bfloat16 cannot hold sub-pixel positions)."""
    return torch.float64 if input.dtype == torch.float64 else torch.float32


def _tap_positions(
    out_h: int,
    out_w: int,
    kernel_h: int,
    kernel_w: int,
    stride_hw: tuple[int, int],
    padding_hw: tuple[int, int],
    dilation_hw: tuple[int, int],
    dtype: torch.dtype,
    device: torch.device,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Undeformed tap positions in input pixels, as output origin + kernel point: the output
    rows' and columns' origins (Ho,), (Wo,) and each kernel point's row and column displacement
    (K,) (kernel point k = i*kw + j sits at row i*dilation, column j*dilation)."""
    rows_o = torch.arange(out_h, device=device, dtype=dtype) * stride_hw[0] - padding_hw[0]
    cols_o = torch.arange(out_w, device=device, dtype=dtype) * stride_hw[1] - padding_hw[1]
    tap_rows_K = torch.arange(kernel_h, device=device, dtype=dtype).repeat_interleave(kernel_w) * dilation_hw[0]
    tap_cols_K = torch.arange(kernel_w, device=device, dtype=dtype).repeat(kernel_h) * dilation_hw[1]
    return rows_o, cols_o, tap_rows_K, tap_cols_K

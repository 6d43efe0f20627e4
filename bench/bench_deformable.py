"""Deformable convolution cost: the grid_sample and gather backends against torchvision's kernel.

Run:  .venv/bin/python bench/bench_deformable.py [--device cpu|cuda] [--repeats 5] [--threads N]

Times forward + backward (gradients for input, offset, mask, weight and bias) of one 3x3
DCNv2 call at the shapes a DM-VQGAN uses on 64x64 images with f = 4 or 8 (feature maps of
32x32, 16x16 and 8x8 with 64-128 channels, batch 8; 8x64x32x32 is the reference shape).
Each figure is the best of ``--repeats`` calls after a warm-up; a plain ``F.conv2d`` of the
same shape gives the floor, and the torchvision/grid_sample ratio is measured in the same
run (absolute times move with the machine's load, ratios much less).
"""

from __future__ import annotations

import argparse
import time
from typing import Callable

import torch
import torch.nn.functional as F

from vqtouch.plugins.tokenizer.deformable import (
    deform_conv2d_gather,
    deform_conv2d_grid_sample,
    deform_conv2d_torchvision,
)

# (batch, channels, height, width); channels in = channels out, as in a ResNet block's second conv.
SHAPES = [(8, 64, 32, 32), (8, 128, 32, 32), (8, 64, 16, 16), (8, 128, 16, 16), (8, 64, 8, 8), (8, 128, 8, 8)]


def best_milliseconds(functions: list[Callable[[], None]], repeats: int, device: torch.device) -> list[float]:
    """Fastest of ``repeats`` timed calls of each function, in ms, after one untimed warm-up call each.

    The functions take turns within every repeat, so a change in the machine's load hits all
    of them alike and their ratios stay meaningful on a shared machine.
    """
    for function in functions:
        function()  # warm-up: allocator, kernel selection, first-call overheads
    best = [float("inf")] * len(functions)
    for _ in range(repeats):
        for index, function in enumerate(functions):
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            start = time.perf_counter()
            function()
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            best[index] = min(best[index], time.perf_counter() - start)
    return [1000.0 * seconds for seconds in best]


def forward_backward(
    deform_conv: Callable | None, shape: tuple[int, int, int, int], device: torch.device
) -> Callable[[], None]:
    """A closure running forward + backward of ``deform_conv`` (None: plain conv2d) on fixed random data."""
    generator = torch.Generator().manual_seed(0)
    batch, channels, height, width = shape
    x = torch.randn(shape, generator=generator).to(device).requires_grad_()
    weight = (0.05 * torch.randn(channels, channels, 3, 3, generator=generator)).to(device).requires_grad_()
    bias = torch.zeros(channels, device=device, requires_grad=True)
    # Non-integer offsets of a couple of pixels and a non-trivial mask: a partly trained layer.
    offset = (2.0 * torch.randn(batch, 18, height, width, generator=generator)).to(device).requires_grad_()
    mask = (2.0 * torch.rand(batch, 9, height, width, generator=generator)).to(device).requires_grad_()
    upstream = torch.randn(batch, channels, height, width, generator=generator).to(device)
    leaves = (x, weight, bias, offset, mask)

    def run() -> None:
        for leaf in leaves:
            leaf.grad = None
        if deform_conv is None:
            out = F.conv2d(x, weight, bias, padding=1)
        else:
            out = deform_conv(x, offset, weight, bias, stride=1, padding=1, dilation=1, mask=mask)
        out.backward(upstream)

    return run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"], help="device to time on")
    parser.add_argument("--repeats", type=int, default=5, help="timed calls per measurement; the best is kept")
    parser.add_argument(
        "--threads",
        type=int,
        default=None,
        help="CPU threads (default: torch's).  On a machine shared with other jobs use 1: "
        "OpenMP with more threads than free cores can run 10-100x slower",
    )
    args = parser.parse_args()
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    import torchvision  # only for the version line; the backend imports it on its own

    where = torch.cuda.get_device_name(device) if device.type == "cuda" else f"cpu, {torch.get_num_threads()} threads"
    print(
        f"torch {torch.__version__}, torchvision {torchvision.__version__}, {where}; "
        f"3x3 DCNv2 forward+backward, float32, best of {args.repeats}"
    )
    header = (
        f"{'B x C x H x W':>16s} {'conv2d ms':>10s} {'grid_sample ms':>15s} {'gather ms':>10s} "
        f"{'torchvision ms':>15s} {'gs / gather':>12s} {'tv / gs':>8s} {'gather / conv2d':>16s}"
    )
    print(header)
    print("-" * len(header))
    for shape in SHAPES:
        conv_ms, grid_ms, gather_ms, vision_ms = best_milliseconds(
            [
                forward_backward(function, shape, device)
                for function in (None, deform_conv2d_grid_sample, deform_conv2d_gather, deform_conv2d_torchvision)
            ],
            args.repeats,
            device,
        )
        label = "x".join(str(n) for n in shape)
        print(
            f"{label:>16s} {conv_ms:10.2f} {grid_ms:15.2f} {gather_ms:10.2f} {vision_ms:15.2f} "
            f"{grid_ms / gather_ms:12.2f} {vision_ms / grid_ms:8.2f} {gather_ms / conv_ms:16.2f}"
        )


if __name__ == "__main__":
    main()

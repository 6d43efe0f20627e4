"""DM-VQGAN against VQGAN, interleaved: training-step time, share of the machine's matmul peak, peak memory.

Run:  OMP_NUM_THREADS=2 .venv/bin/python bench/bench_dm_vqgan.py [--size 64] [--rounds 15] [--device cpu]

- The machine's fp32 peaks: the best of several 2048 x 2048 matrix products, and of a 3x3
  128-channel convolution forward, in GFLOP/s; each contender's share is given of both (on some
  CPUs the convolution library outruns the matrix product, and the convolution share is the stricter).
- Every contender (VQGAN, DM-VQGAN with each pure-PyTorch deformable backend, and both at
  taming-transformers' ImageNet f16 configuration, ``TAMING_F16``) is built once in
  this process; each round times one training step of every contender, in a rotated order, so
  a change of the machine's load hits all of them alike.  Reported: the median step time, the
  median of the per-round ratios to VQGAN at the same configuration (paired), and the share of
  each peak = the step's matmul/convolution FLOPs (forward and backward, counted by
  ``torch.utils.flop_counter``; the deformable gathers count nothing) / the median step time /
  the peak.
- Peak memory: each contender trains a few steps in a fresh interpreter; its peak RSS (CPU) or
  ``max_memory_allocated`` (CUDA) is reported beside the RSS of ``import torch`` alone, which
  the CUDA build of torch makes large.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time

import torch

#: taming-transformers' ImageNet VQGAN (vqgan_imagenet_f16_1024: ch 128, ch_mult 1,1,2,2,4, 2 ResNet blocks,
#: attention at 16 px, z and embed 256); vqtouch's VQGAN has its parameter count at this config.
TAMING_F16 = {
    "channels": 128,
    "channel_multipliers": [1, 1, 2, 2, 4],
    "num_res_blocks": 2,
    "attention_resolutions": [16],
    "z_channels": 256,
    "embed_dim": 256,
}
CONTENDERS = {
    "vqgan": {"name": "vqgan"},
    "dm_vqgan (grid_sample)": {"name": "dm_vqgan", "deformable_backend": "grid_sample"},
    "dm_vqgan (gather)": {"name": "dm_vqgan", "deformable_backend": "gather"},
    "vqgan, taming f16": {"name": "vqgan", **TAMING_F16},
    "dm_vqgan (gather), taming f16": {"name": "dm_vqgan", "deformable_backend": "gather", **TAMING_F16},
}

MEMORY_WORKER = r"""
import json, sys

def high_water_mb():
    # VmHWM belongs to this process image; ru_maxrss would carry the parent's peak across exec.
    with open("/proc/self/status") as status:
        return next(int(line.split()[1]) for line in status if line.startswith("VmHWM")) / 1024

import torch
args = json.loads(sys.argv[1])
baseline_mb = high_water_mb()
sys.path.insert(0, args["bench"])
from bench_dm_vqgan import build, train_step
device = torch.device(args["device"])
step = train_step(*build(args["config"], args["size"], args["batch"], args["channels"], device))
for _ in range(3):
    step()
if device.type == "cuda":
    peak = torch.cuda.max_memory_allocated() / 2**20
else:
    peak = high_water_mb()
print(json.dumps({"import_torch_mb": baseline_mb, "peak_mb": peak}))
"""


def build(config: dict, size: int, batch: int, channels: int, device: torch.device) -> tuple:
    """A tokenizer (autoencoder + 512-code VQ), its optimizer and a batch of images in [-1, 1]."""
    from vqtouch.core import BuildContext, load_plugins

    torch.manual_seed(0)
    host = load_plugins(autoload=False)
    context = BuildContext(image_size=size)
    encoder = host.build("autoencoder", {"channels": channels, **config}, context).to(device)
    quantizer = host.build(
        "quantizer",
        {"name": "vq", "codebook_size": 512},
        context.model_copy(update={"latent_dim": encoder.latent_channels}),
    ).to(device)
    optimizer = torch.optim.AdamW(list(encoder.parameters()) + list(quantizer.parameters()), lr=1e-4)
    images = torch.rand(batch, 3, size, size, device=device) * 2 - 1
    return encoder, quantizer, optimizer, images


def train_step(encoder, quantizer, optimizer, images):
    """One L1 + VQ training step of the tokenizer, as a callable."""

    def step() -> None:
        output = quantizer(encoder.encode(images))
        loss = (encoder.decode(output.quantized_BDhw) - images).abs().mean() + output.loss
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()

    return step


def matmul_peak_gflops(
    device: torch.device, size: int = 2048, repeats: int = 10, dtype: torch.dtype = torch.float32
) -> float:
    """The best GFLOP/s of a size x size matrix product in ``dtype`` on ``device``."""
    a = torch.randn(size, size, device=device).to(dtype)
    b = torch.randn(size, size, device=device).to(dtype)
    best = float("inf")
    for _ in range(repeats + 2):
        sync(device)
        tic = time.perf_counter()
        a @ b
        sync(device)
        best = min(best, time.perf_counter() - tic)
    return 2 * size**3 / best / 1e9


def conv_peak_gflops(device: torch.device, repeats: int = 10) -> float:
    """The best fp32 GFLOP/s of a 3x3, 128-channel convolution forward on 8 x 32 x 32 (on some CPUs
    the convolution library outruns the matrix product)."""
    conv = torch.nn.Conv2d(128, 128, 3, padding=1, bias=False).to(device)
    x = torch.randn(8, 128, 32, 32, device=device)
    best = float("inf")
    with torch.no_grad():
        for _ in range(repeats + 2):
            sync(device)
            tic = time.perf_counter()
            conv(x)
            sync(device)
            best = min(best, time.perf_counter() - tic)
    return 2 * 8 * 128 * 128 * 9 * 32 * 32 / best / 1e9


def sync(device: torch.device) -> None:
    """Wait for the device's queued work (a no-op on the CPU), so a timer measures it."""
    if device.type == "cuda":
        torch.cuda.synchronize()


def counted_flops(step) -> float:
    """Matmul and convolution FLOPs of one call of ``step`` (forward and backward)."""
    from torch.utils.flop_counter import FlopCounterMode

    with FlopCounterMode(display=False) as counter:
        step()
    return float(counter.get_total_flops())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    parser.add_argument("--size", type=int, default=64, help="image side (default 64)")
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--channels", type=int, default=64, help="base channels (the scene's default 64)")
    parser.add_argument("--rounds", type=int, default=15, help="interleaved timing rounds (default 15)")
    parser.add_argument("--no-taming", action="store_true", help="leave out the two taming-f16 contenders")
    args = parser.parse_args()
    if args.no_taming:
        for label in [label for label in CONTENDERS if "taming" in label]:
            del CONTENDERS[label]
    device = torch.device(args.device)
    matmul_peak, conv_peak = matmul_peak_gflops(device), conv_peak_gflops(device)
    where = torch.cuda.get_device_name(device) if device.type == "cuda" else f"cpu, {torch.get_num_threads()} threads"
    print(f"torch {torch.__version__}, {where}; {args.size} px, batch {args.batch}, base channels {args.channels}")
    print(
        f"fp32 peaks: matmul {matmul_peak:.1f} GFLOP/s (best 2048x2048 product), 3x3 conv {conv_peak:.1f} GFLOP/s "
        f"(128 ch, 32 px, forward)"
    )
    steps = {
        label: train_step(*build(config, args.size, args.batch, args.channels, device))
        for label, config in CONTENDERS.items()
    }
    flops = {label: counted_flops(step) for label, step in steps.items()}
    for step in steps.values():  # warm-up
        step()
    times: dict[str, list[float]] = {label: [] for label in steps}
    labels = list(steps)
    for round_index in range(args.rounds):
        order = labels[round_index % len(labels) :] + labels[: round_index % len(labels)]
        for label in order:
            sync(device)
            tic = time.perf_counter()
            steps[label]()
            sync(device)
            times[label].append(time.perf_counter() - tic)
    bench_folder = str(__import__("pathlib").Path(__file__).resolve().parent)
    header = (
        f"{'contender':30s} {'step ms':>8s} {'x VQGAN':>8s} {'GFLOP':>7s} {'% matmul':>8s} {'% conv':>7s} "
        f"{'peak MB':>8s} {'import torch MB':>15s}"
    )
    print(header)
    print("-" * len(header))
    for label in labels:
        median = statistics.median(times[label])
        baseline = "vqgan, taming f16" if "taming" in label else "vqgan"  # VQGAN at the same configuration
        paired = statistics.median(t / v for t, v in zip(times[label], times[baseline]))
        memory = json.loads(
            subprocess.run(
                [
                    sys.executable,
                    "-c",
                    MEMORY_WORKER,
                    json.dumps(
                        {
                            "bench": bench_folder,
                            "config": CONTENDERS[label],
                            "size": args.size,
                            "batch": args.batch,
                            "channels": args.channels,
                            "device": args.device,
                        }
                    ),
                ],
                capture_output=True,
                text=True,
                check=True,
            )
            .stdout.strip()
            .splitlines()[-1]
        )
        gflops = flops[label] / median / 1e9
        print(
            f"{label:30s} {median * 1e3:8.1f} {paired:8.2f} {flops[label] / 1e9:7.2f} {gflops / matmul_peak:8.1%} "
            f"{gflops / conv_peak:7.1%} {memory['peak_mb']:8.0f} {memory['import_torch_mb']:15.0f}"
        )


if __name__ == "__main__":
    main()

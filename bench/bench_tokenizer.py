"""Tokenizer speed and memory at any resolution: training and inference throughput, FLOPs and peak
memory of VQGAN and DM-VQGAN, with and without the mid-block attention.

Run:  .venv/bin/python bench/bench_tokenizer.py [--device cpu|cuda] [--sizes 64 128 256 240x320]
      [--batch 8] [--channels 64] [--repeats 3] [--backends gather grid_sample] [--no-mid-attention]

- Every configuration runs twice, each time in a fresh interpreter: once training (AdamW, L1 +
  VQ loss) and once for inference only (encode + quantize, decode, under ``torch.no_grad``), so
  the peak memory of each is its own: the process's high-water RSS (``VmHWM``; on CUDA
  ``max_memory_allocated``).  ``import torch`` alone is reported apart (the CUDA build of torch
  is several hundred MB before any model exists).
- Throughputs are the best of ``--repeats`` timed steps after one warm-up step.  Configurations
  run one after another, not interleaved: compare ratios within one run
  (``bench/bench_dm_vqgan.py`` interleaves VQGAN and DM-VQGAN for the paired training ratio).
- GFLOP: matmul and convolution FLOPs of one training step (forward and backward), counted by
  ``torch.utils.flop_counter``; with ``--no-mid-attention`` the difference to the same encoder
  with it is the mid-block attention's share (its tokens: (H/f) x (W/f), 4096 at 256 px, f = 4).
- Sizes are S (S x S) or HEIGHTxWIDTH, e.g. 240x320, a GelSight frame's native 3:4 aspect.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

WORKER = r"""
import json, sys, time, torch

def high_water_mb():
    # VmHWM belongs to this process image; ru_maxrss would carry the parent's peak across exec.
    with open("/proc/self/status") as status:
        return next(int(line.split()[1]) for line in status if line.startswith("VmHWM")) / 1024

import_torch_mb = high_water_mb()
from vqtouch.core import BuildContext, load_plugins
from vqtouch.core.image_size import image_hw
args = json.loads(sys.argv[1])
torch.manual_seed(0)
device = torch.device(args["device"])
host = load_plugins(autoload=False)
size = args["size"] if isinstance(args["size"], int) else tuple(args["size"])
context = BuildContext(image_size=size)
encoder = host.build("autoencoder", {"name": args["encoder"], "channels": args["channels"], **args["options"]},
                     context).to(device)
quantizer = host.build("quantizer", {"name": "vq", "codebook_size": 512},
                       context.model_copy(update={"latent_dim": encoder.latent_channels})).to(device)
images = torch.rand(args["batch"], 3, *image_hw(size), device=device) * 2 - 1

def sync():
    if device.type == "cuda":
        torch.cuda.synchronize()

def best(fn):
    fn(); sync()
    times = []
    for _ in range(args["repeats"]):
        tic = time.perf_counter(); fn(); sync(); times.append(time.perf_counter() - tic)
    return args["batch"] / min(times)

result = {"params_m": sum(p.numel() for p in encoder.parameters()) / 1e6, "import_torch_mb": import_torch_mb}
if args["mode"] == "train":
    from torch.utils.flop_counter import FlopCounterMode
    optimizer = torch.optim.AdamW(list(encoder.parameters()) + list(quantizer.parameters()), lr=1e-4)

    def train_step():
        output = quantizer(encoder.encode(images))
        loss = (encoder.decode(output.quantized_BDhw) - images).abs().mean() + output.loss
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()

    with FlopCounterMode(display=False) as counter:
        train_step()
    result["gflop"] = counter.get_total_flops() / 1e9
    result["train"] = best(train_step)
else:
    encoder.eval(); quantizer.eval()
    with torch.no_grad():
        latents = quantizer(encoder.encode(images)).quantized_BDhw
        result["encode"] = best(lambda: quantizer(encoder.encode(images)))
        result["decode"] = best(lambda: encoder.decode(latents))
if device.type == "cuda":
    result["peak_mb"] = torch.cuda.max_memory_allocated() / 2**20
else:
    result["peak_mb"] = high_water_mb()
print(json.dumps(result))
"""


def measure(settings: dict) -> dict:
    """Run one configuration in one mode ("train" or "infer") in a fresh interpreter; its measurements."""
    completed = subprocess.run([sys.executable, "-c", WORKER, json.dumps(settings)], capture_output=True, text=True)
    if completed.returncode != 0:
        raise SystemExit(completed.stderr[-2000:])
    return json.loads(completed.stdout.strip().splitlines()[-1])


def contenders(backends: list[str], no_mid_attention: bool) -> list[tuple[str, str, dict]]:
    """(label, autoencoder, options) of every configuration measured at each size."""
    rows = [("vqgan", "vqgan", {})]
    rows += [(f"dm_vqgan ({backend})", "dm_vqgan", {"deformable_backend": backend}) for backend in backends]
    if no_mid_attention:
        rows += [
            ("vqgan, no mid attn", "vqgan", {"mid_attention": False}),
            (
                f"dm_vqgan ({backends[0]}), no mid attn",
                "dm_vqgan",
                {"deformable_backend": backends[0], "mid_attention": False},
            ),
        ]
    return rows


def main() -> None:
    from vqtouch.core.image_size import image_hw, image_size_argument, size_text

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    parser.add_argument(
        "--sizes",
        type=image_size_argument,
        nargs="+",
        default=[64, 128],
        help="image sizes, S or HEIGHTxWIDTH (default 64 128)",
    )
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--channels", type=int, default=64, help="base channels of both encoders (scene default 64)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--backends",
        nargs="+",
        default=["gather", "grid_sample"],
        choices=["gather", "grid_sample", "torchvision"],
        help="DM-VQGAN's deformable backends",
    )
    parser.add_argument(
        "--no-mid-attention",
        action="store_true",
        help="also measure VQGAN and DM-VQGAN without the mid-block attention (mid_attention=false)",
    )
    args = parser.parse_args()
    print(
        f"device {args.device}, batch {args.batch}, base channels {args.channels}, codebook 512 (vq); "
        "peak MB includes import torch"
    )
    header = (
        f"{'size':>7s} {'encoder':30s} {'params M':>8s} {'GFLOP':>7s} {'train img/s':>11s} {'train MB':>8s} "
        f"{'encode img/s':>12s} {'decode img/s':>12s} {'infer MB':>8s}  cost vs VQGAN (train, encode, decode)"
    )
    print(header)
    print("-" * len(header))
    results: list[dict] = []
    for size in args.sizes:
        by_label = {}
        for label, encoder, options in contenders(args.backends, args.no_mid_attention):
            settings = {
                "encoder": encoder,
                "options": options,
                "size": size,
                "batch": args.batch,
                "channels": args.channels,
                "device": args.device,
                "repeats": args.repeats,
            }
            train, infer = measure({**settings, "mode": "train"}), measure({**settings, "mode": "infer"})
            r = by_label[label] = {
                "size": list(image_hw(size)),
                "encoder": label,
                **train,
                "train_peak_mb": train.pop("peak_mb"),
                "encode": infer["encode"],
                "decode": infer["decode"],
                "infer_peak_mb": infer["peak_mb"],
            }
            r.pop("peak_mb", None)
            v = by_label["vqgan"]
            ratio = (
                ""
                if label == "vqgan"
                else "  " + ", ".join(f"{v[k] / r[k]:.2f}x" for k in ("train", "encode", "decode"))
            )
            print(
                f"{size_text(size):>7s} {label:30s} {r['params_m']:8.2f} {r['gflop']:7.1f} {r['train']:11.2f} "
                f"{r['train_peak_mb']:8.0f} {r['encode']:12.1f} {r['decode']:12.1f} {r['infer_peak_mb']:8.0f}{ratio}",
                flush=True,
            )
            results.append(r)
    print(f"import torch alone: {results[0]['import_torch_mb']:.0f} MB RSS")
    print(json.dumps(results))


if __name__ == "__main__":
    main()

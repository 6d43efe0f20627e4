"""Tokenizer speed and memory: training, encode and decode throughput, DM-VQGAN vs VQGAN.

Run:  .venv/bin/python bench/bench_tokenizer.py [--device cpu|cuda] [--sizes 64 128] [--batch 8]

Each configuration runs in a fresh subprocess, so its peak memory (max RSS on CPU,
``max_memory_allocated`` on CUDA) is its own.  Throughputs are the best of ``--repeats``
timed steps after warm-up; the last column is each DM-VQGAN figure divided by the VQGAN one
measured in the same run (the ratio is what to compare across machines).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

WORKER = r"""
import json, resource, sys, time, torch
from vqtouch.core import BuildContext, load_plugins
args = json.loads(sys.argv[1])
torch.manual_seed(0)
device = torch.device(args["device"])
host = load_plugins(autoload=False)
context = BuildContext(image_size=args["size"])
encoder = host.build("autoencoder", {"name": args["encoder"], "channels": args["channels"], **args["options"]},
                     context).to(device)
quantizer = host.build("quantizer", {"name": "vq", "codebook_size": 512},
                       context.model_copy(update={"latent_dim": encoder.latent_channels})).to(device)
params = list(encoder.parameters()) + list(quantizer.parameters())
optimizer = torch.optim.AdamW(params, lr=1e-4)
images = torch.rand(args["batch"], 3, args["size"], args["size"], device=device) * 2 - 1

def sync():
    if device.type == "cuda":
        torch.cuda.synchronize()

def train_step():
    output = quantizer(encoder.encode(images))
    loss = (encoder.decode(output.quantized_BDhw) - images).abs().mean() + output.loss
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    optimizer.step()

def best(fn):
    fn(); sync()
    times = []
    for _ in range(args["repeats"]):
        tic = time.perf_counter(); fn(); sync(); times.append(time.perf_counter() - tic)
    return args["batch"] / min(times)

result = {"params_m": sum(p.numel() for p in encoder.parameters()) / 1e6, "train": best(train_step)}
with torch.no_grad():
    latents = encoder.encode(images)
    result["encode"] = best(lambda: quantizer(encoder.encode(images)))
    result["decode"] = best(lambda: encoder.decode(latents))
if device.type == "cuda":
    result["peak_mb"] = torch.cuda.max_memory_allocated() / 2**20
else:
    result["peak_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps(result))
"""


def measure(settings: dict) -> dict:
    """Run one configuration in a fresh interpreter and return its measurements."""
    completed = subprocess.run([sys.executable, "-c", WORKER, json.dumps(settings)], capture_output=True, text=True)
    if completed.returncode != 0:
        raise SystemExit(completed.stderr[-2000:])
    return json.loads(completed.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 128])
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--channels", type=int, default=64, help="base channels of both encoders (scene default 64)")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    header = (f"{'size':>4s} {'encoder':9s} {'params M':>8s} {'train img/s':>11s} {'encode img/s':>12s} "
              f"{'decode img/s':>12s} {'peak MB':>8s}  DM/VQGAN cost (train, encode, decode)")
    print(f"device {args.device}, batch {args.batch}, base channels {args.channels}, codebook 512 (vq)")
    print(header)
    print("-" * len(header))
    # DM-VQGAN once per deformable backend that needs no extra package (torchvision's is far slower on CPU).
    contenders = [("vqgan", "vqgan", {}), ("dm_vqgan", "dm_vqgan", {"deformable_backend": "grid_sample"}),
                  ("dm/gather", "dm_vqgan", {"deformable_backend": "gather"})]
    for size in args.sizes:
        results = {}
        for label, encoder, options in contenders:
            results[label] = measure({"encoder": encoder, "options": options, "size": size, "batch": args.batch,
                                      "channels": args.channels, "device": args.device, "repeats": args.repeats})
            r = results[label]
            ratio = ""
            if label != "vqgan":
                v = results["vqgan"]
                ratio = "  " + ", ".join(f"{v[k] / r[k]:.2f}x" for k in ("train", "encode", "decode"))
            print(f"{size:4d} {label:9s} {r['params_m']:8.2f} {r['train']:11.1f} {r['encode']:12.1f} "
                  f"{r['decode']:12.1f} {r['peak_mb']:8.0f}{ratio}")


if __name__ == "__main__":
    main()

"""fp32 against bf16, the machine and the project in one run: matmul peaks, then the training and
sampling steps of the tokenizer and the generator, interleaved.

Run:  .venv/bin/python bench/bench_precision.py [--threads 2] [--rounds 5] [--batch 16] [--json out.json]

- **The machine**: the best fp32 and bf16 GFLOP/s of n x n matrix products (n = 512, 1024, 2048);
  the largest bf16 figure is "the bf16 peak" every share below is of.
- **Contenders**, each in fp32 and under ``torch.autocast("cpu", dtype=torch.bfloat16)`` (what
  ``precision: bf16`` does; the quantizer's distances stay fp32 inside it, as in training):
  the tokenizer's training step (L1 + VQ, AdamW; VQGAN and DM-VQGAN at the bundled size, 32
  base channels and 64 px, and at 128 px), and the generator's training step (loss, backward,
  AdamW, label conditioner) and sampling step (one denoiser pass under ``no_grad``) of the
  shipped ``pretrained:tour`` and ``pretrained:tour_wide`` networks.
- Every round times one call of every contender in a rotated order, so the machine's drift hits
  all alike; reported: the median ms per step, images per second, the median of the per-round
  fp32/bf16 ratios (paired), the step's matmul and convolution FLOPs (``torch.utils.flop_counter``,
  forward and backward) per second and its share of the bf16 peak.

Say the machine's load beside the figures: two torch jobs on two cores slow each other far more
than twice.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_dm_vqgan import build, counted_flops, train_step  # noqa: E402

PRECISIONS = ("fp32", "bf16")


def autocast(precision: str) -> contextlib.AbstractContextManager:
    """What a component's ``precision`` does on the CPU."""
    return torch.autocast("cpu", dtype=torch.bfloat16) if precision == "bf16" else contextlib.nullcontext()


def matmul_gflops(size: int, dtype: torch.dtype, repeats: int = 8) -> float:
    """The best GFLOP/s of a size x size product in ``dtype``."""
    a, b = torch.randn(size, size).to(dtype), torch.randn(size, size).to(dtype)
    best = float("inf")
    for _ in range(repeats + 2):
        tic = time.perf_counter()
        a @ b
        best = min(best, time.perf_counter() - tic)
    return 2 * size**3 / best / 1e9


def tokenizer_steps(name: str, size: int, batch: int) -> dict[str, callable]:
    """One tokenizer's training step in each precision (the same weights, optimizer and images)."""
    config = {"name": name, **({"deformable_backend": "gather"} if name == "dm_vqgan" else {})}
    encoder, quantizer, optimizer, images = build(config, size, batch, 32, torch.device("cpu"))
    plain = train_step(encoder, quantizer, optimizer, images)

    def in_precision(precision: str):
        def step() -> None:
            with autocast(precision):
                latents = encoder.encode(images)
            output = quantizer(latents.float())  # fp32 inside, as TokenizerTask does
            with autocast(precision):
                reconstruction = encoder.decode(output.quantized_BDhw)
            loss = (reconstruction.float() - images).abs().mean() + output.loss
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()

        return step if precision == "bf16" else plain

    return {precision: in_precision(precision) for precision in PRECISIONS}


def generator_steps(bundle: str, batch: int) -> tuple[dict[str, callable], dict[str, callable]]:
    """The training and the sampling step of a bundle's generator with its label conditioner."""
    from vqtouch.core import load_plugins
    from vqtouch.plugins.generator import load_pipeline

    torch.manual_seed(0)
    pipe = load_pipeline(f"pretrained:{bundle}", host=load_plugins())
    generator, conditioner = pipe.generator, pipe.conditioners[0]
    height, width = generator.grid_hw
    codes_BHW = torch.randint(0, generator.num_codes, (batch, height, width))
    labels_B = torch.randint(0, len(pipe.class_names), (batch,))
    params = [p for module in (generator, conditioner) for p in module.parameters()]
    optimizer = torch.optim.AdamW(params, lr=1e-4)

    def train(precision: str):
        def step() -> None:
            generator.train()
            conditioner.train()
            with autocast(precision):
                loss, _ = generator.training_loss(codes_BHW, conditioner(labels_B))
            optimizer.zero_grad(set_to_none=True)
            loss.float().backward()
            optimizer.step()

        return step

    timestep_B = torch.full((batch,), generator.config.num_steps // 2)

    def sample(precision: str):
        @torch.no_grad()
        def step() -> None:
            generator.eval()
            conditioner.eval()
            with autocast(precision):
                condition = conditioner(labels_B)
                generator.network(
                    codes_BHW.flatten(1), timestep_B, condition=condition.tokens_BND, condition_grid=condition.grid_BDhw
                )

        return step

    return {p: train(p) for p in PRECISIONS}, {p: sample(p) for p in PRECISIONS}


def contenders(batch: int, bundles: list[str]) -> dict[str, tuple[dict[str, callable], int]]:
    """Every contender's steps by precision, with its images per step."""
    table: dict[str, tuple[dict[str, callable], int]] = {}
    for name in ("vqgan", "dm_vqgan"):
        for size in (64, 128):
            table[f"tokenizer train, {name}, {size} px"] = (tokenizer_steps(name, size, batch), batch)
    for bundle in bundles:
        train, sample = generator_steps(bundle, batch)
        table[f"generator train, {bundle}"] = (train, batch)
        table[f"generator sampling step, {bundle}"] = (sample, batch)
    return table


def measure(table: dict, rounds: int) -> dict[str, dict[str, list[float]]]:
    """Seconds per call of every (contender, precision), ``rounds`` interleaved rounds in rotated order."""
    calls = [(label, precision) for label in table for precision in PRECISIONS]
    for label, precision in calls:  # warm-up: allocator, autocast caches, oneDNN kernels
        table[label][0][precision]()
    seconds: dict[str, dict[str, list[float]]] = {label: {p: [] for p in PRECISIONS} for label in table}
    for round_index in range(rounds):
        order = calls[round_index % len(calls) :] + calls[: round_index % len(calls)]
        for label, precision in order:
            tic = time.perf_counter()
            table[label][0][precision]()
            seconds[label][precision].append(time.perf_counter() - tic)
    return seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=5, help="interleaved timing rounds (default 5)")
    parser.add_argument("--batch", type=int, default=16)
    parser.add_argument("--bundles", nargs="+", default=["tour", "tour_wide"])
    parser.add_argument("--json", help="also write every measurement to this file")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    peaks = {
        (size, dtype_name): matmul_gflops(size, dtype)
        for size in (512, 1024, 2048)
        for dtype_name, dtype in (("fp32", torch.float32), ("bf16", torch.bfloat16))
    }
    bf16_peak = max(value for (_, name), value in peaks.items() if name == "bf16")
    print(f"torch {torch.__version__}, cpu, {torch.get_num_threads()} threads, batch {args.batch}")
    print("| matmul n | fp32 GFLOP/s | bf16 GFLOP/s | bf16 / fp32 |\n|---|---|---|---|")
    for size in (512, 1024, 2048):
        fp32, bf16 = peaks[(size, "fp32")], peaks[(size, "bf16")]
        print(f"| {size} | {fp32:.0f} | {bf16:.0f} | {bf16 / fp32:.2f} |")
    table = contenders(args.batch, args.bundles)
    flops = {label: counted_flops(steps["fp32"]) for label, (steps, _) in table.items()}
    seconds = measure(table, args.rounds)
    print(
        "\n| step | fp32 ms | bf16 ms | fp32 / bf16 (paired) | bf16 img/s | GFLOP per step | bf16 GFLOP/s | "
        f"share of the bf16 peak ({bf16_peak:.0f}) |\n|---|---|---|---|---|---|---|---|"
    )
    rows = []
    for label, (_, images) in table.items():
        fp32, bf16 = (statistics.median(seconds[label][p]) for p in PRECISIONS)
        ratio = statistics.median(a / b for a, b in zip(seconds[label]["fp32"], seconds[label]["bf16"]))
        achieved = flops[label] / bf16 / 1e9
        rows.append({"step": label, "fp32_s": fp32, "bf16_s": bf16, "ratio": ratio, "gflop": flops[label] / 1e9})
        print(
            f"| {label} | {fp32 * 1e3:.0f} | {bf16 * 1e3:.0f} | {ratio:.2f} | {images / bf16:.1f} | "
            f"{flops[label] / 1e9:.1f} | {achieved:.0f} | {achieved / bf16_peak:.1%} |"
        )
    if args.json:
        record = {"peaks": {f"{size} {name}": value for (size, name), value in peaks.items()}, "rows": rows}
        Path(args.json).write_text(json.dumps(record, indent=2) + "\n")


if __name__ == "__main__":
    main()

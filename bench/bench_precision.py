"""fp32 against bf16, the machine and the project in one run: matmul peaks, then the training and
sampling steps of the tokenizer and the generator, interleaved.

Run:  .venv/bin/python bench/bench_precision.py [--threads 2] [--rounds 5] [--batch 16] [--json out.json]

- **The machine**: the best fp32 and bf16 GFLOP/s of n x n matrix products (n = 512, 1024, 2048);
  the largest bf16 figure is "the bf16 peak" every share below is of.
- **Contenders**: the tokenizer's training step (L1 + VQ, AdamW; VQGAN and DM-VQGAN at the
  bundled size, 32 base channels and 64 px, and at 128 px), and the generator's training step
  (loss, backward, AdamW, label conditioner) and sampling step (one denoiser pass under
  ``no_grad``) of the shipped ``pretrained:tour`` and ``pretrained:tour_wide`` networks.
- **Variants** of each: ``fp32`` and ``bf16`` as the trainer runs them now (Adam's fused kernel;
  ``precision: bf16`` is ``torch.autocast("cpu", dtype=torch.bfloat16)``, the quantizer's distances
  fp32 inside it; the denoiser's :func:`~vqtouch.plugins.generator.denoiser.attend` takes its
  explicit form for bf16 training), and the training steps as they ran before: ``fp32 before``
  (per-tensor Adam) and, for the generator, ``bf16 autocast alone`` (per-tensor Adam, the fused
  attention kernel), so the levers' shares show.
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
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_dm_vqgan import build, counted_flops  # noqa: E402

#: The training-step variants; sampling steps have only fp32 and bf16.
TRAIN_VARIANTS = ("fp32 before", "fp32", "bf16")
GENERATOR_VARIANTS = ("fp32 before", "fp32", "bf16 autocast alone", "bf16")


def autocast(precision: str) -> contextlib.AbstractContextManager:
    """What a component's ``precision`` does on the CPU."""
    return torch.autocast("cpu", dtype=torch.bfloat16) if precision.startswith("bf16") else contextlib.nullcontext()


def adamw(params: list, variant: str) -> torch.optim.Optimizer:
    """The optimizer a variant trains with: the trainer's fused Adam, or the per-tensor loops it replaced."""
    fused = not variant.endswith(("before", "alone"))
    return torch.optim.AdamW(params, lr=1e-4, **({"fused": True} if fused else {"foreach": True}))


@contextlib.contextmanager
def fused_attention_only(variant: str):
    """For ``bf16 autocast alone``: the denoiser's attention through the fused kernel in every case."""
    from vqtouch.plugins.generator import denoiser

    if variant != "bf16 autocast alone":
        yield
        return
    explicit = denoiser.attend
    denoiser.attend = lambda q, k, v, mask=None, dropout=0.0: F.scaled_dot_product_attention(q, k, v, attn_mask=mask)
    try:
        yield
    finally:
        denoiser.attend = explicit


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
    """One tokenizer's training step in each variant (the same weights and images)."""
    config = {"name": name, **({"deformable_backend": "gather"} if name == "dm_vqgan" else {})}
    encoder, quantizer, _, images = build(config, size, batch, 32, torch.device("cpu"))
    params = list(encoder.parameters()) + list(quantizer.parameters())

    def in_variant(variant: str):
        optimizer = adamw(params, variant)

        def step() -> None:
            with autocast(variant):
                latents = encoder.encode(images)
            output = quantizer(latents.float())  # fp32 inside, as TokenizerTask does
            with autocast(variant):
                reconstruction = encoder.decode(output.quantized_BDhw)
            loss = (reconstruction.float() - images).abs().mean() + output.loss
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()

        return step

    return {variant: in_variant(variant) for variant in TRAIN_VARIANTS}


def generator_steps(bundle: str, batch: int) -> tuple[dict[str, callable], dict[str, callable]]:
    """The training step (each variant) and the sampling step (fp32, bf16) of a bundle's generator
    with its label conditioner."""
    from vqtouch.core import load_plugins
    from vqtouch.plugins.generator import load_pipeline

    torch.manual_seed(0)
    pipe = load_pipeline(f"pretrained:{bundle}", host=load_plugins())
    generator, conditioner = pipe.generator, pipe.conditioners[0]
    height, width = generator.grid_hw
    codes_BHW = torch.randint(0, generator.num_codes, (batch, height, width))
    labels_B = torch.randint(0, len(pipe.class_names), (batch,))
    params = [p for module in (generator, conditioner) for p in module.parameters()]

    def train(variant: str):
        optimizer = adamw(params, variant)

        def step() -> None:
            generator.train()
            conditioner.train()
            with fused_attention_only(variant), autocast(variant):
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

    return {v: train(v) for v in GENERATOR_VARIANTS}, {p: sample(p) for p in ("fp32", "bf16")}


def contenders(batch: int, bundles: list[str]) -> dict[str, tuple[dict[str, callable], int]]:
    """Every contender's steps by variant, with its images per step."""
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
    """Seconds per call of every (contender, variant), ``rounds`` interleaved rounds in rotated order."""
    calls = [(label, variant) for label, (steps, _) in table.items() for variant in steps]
    for label, variant in calls:  # warm-up: allocator, autocast caches, oneDNN kernels
        table[label][0][variant]()
    seconds: dict[str, dict[str, list[float]]] = {label: {v: [] for v in steps} for label, (steps, _) in table.items()}
    for round_index in range(rounds):
        order = calls[round_index % len(calls) :] + calls[: round_index % len(calls)]
        for label, variant in order:
            tic = time.perf_counter()
            table[label][0][variant]()
            seconds[label][variant].append(time.perf_counter() - tic)
    return seconds


def paired_ratio(seconds: dict[str, list[float]], slow: str, fast: str) -> float:
    """The median of the per-round ``slow / fast`` time ratios."""
    return statistics.median(a / b for a, b in zip(seconds[slow], seconds[fast]))


def print_peaks(peaks: dict) -> float:
    """The matmul table; returns the bf16 peak."""
    print("| matmul n | fp32 GFLOP/s | bf16 GFLOP/s | bf16 / fp32 |\n|---|---|---|---|")
    for size in (512, 1024, 2048):
        fp32, bf16 = peaks[(size, "fp32")], peaks[(size, "bf16")]
        print(f"| {size} | {fp32:.0f} | {bf16:.0f} | {bf16 / fp32:.2f} |")
    return max(value for (_, name), value in peaks.items() if name == "bf16")


def _ms(value: float | None) -> str:
    return "-" if value is None else f"{value * 1e3:.0f}"


def print_steps(table: dict, seconds: dict, flops: dict, bf16_peak: float) -> list[dict]:
    """The per-step table (the training steps against how they ran before); returns its rows."""
    print(
        "\n| step | fp32 before ms | fp32 ms | bf16 ms | before / bf16 (paired) | fp32 / bf16 (paired) | "
        f"bf16 img/s | GFLOP per step | bf16 GFLOP/s | share of the bf16 peak ({bf16_peak:.0f}) |\n"
        "|---|---|---|---|---|---|---|---|---|---|"
    )
    rows = []
    for label, (_, images) in table.items():
        times = {variant: statistics.median(values) for variant, values in seconds[label].items()}
        before = times.get("fp32 before")
        achieved = flops[label] / times["bf16"] / 1e9
        row = {"step": label, **{f"{variant} s": value for variant, value in times.items()}}
        row["gflop"] = flops[label] / 1e9
        row["fp32 / bf16"] = paired_ratio(seconds[label], "fp32", "bf16")
        row["before / bf16"] = paired_ratio(seconds[label], "fp32 before", "bf16") if before else None
        rows.append(row)
        speedup = "-" if before is None else f"{row['before / bf16']:.2f}"
        print(
            f"| {label} | {_ms(before)} | {_ms(times['fp32'])} | {_ms(times['bf16'])} | {speedup} | "
            f"{row['fp32 / bf16']:.2f} | {images / times['bf16']:.1f} | {row['gflop']:.1f} | {achieved:.0f} | "
            f"{achieved / bf16_peak:.1%} |"
        )
    return rows


def print_levers(table: dict, seconds: dict) -> None:
    """What each lever gave the generator's training step: every variant against ``fp32 before``."""
    header = " | ".join(GENERATOR_VARIANTS)
    print(f"\n| generator training step | {header} |\n|---|" + "---|" * len(GENERATOR_VARIANTS))
    for label in table:
        if label.startswith("generator train"):
            cells = [
                f"{_ms(statistics.median(seconds[label][v]))} ms "
                f"({paired_ratio(seconds[label], 'fp32 before', v):.2f}x)"
                for v in GENERATOR_VARIANTS
            ]
            print(f"| {label.split(', ')[1]} | " + " | ".join(cells) + " |")


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
    print(f"torch {torch.__version__}, cpu, {torch.get_num_threads()} threads, batch {args.batch}")
    bf16_peak = print_peaks(peaks)
    table = contenders(args.batch, args.bundles)
    flops = {label: counted_flops(steps["fp32"]) for label, (steps, _) in table.items()}
    seconds = measure(table, args.rounds)
    rows = print_steps(table, seconds, flops, bf16_peak)
    print_levers(table, seconds)
    if args.json:
        record = {"peaks": {f"{size} {name}": value for (size, name), value in peaks.items()}, "rows": rows}
        Path(args.json).write_text(json.dumps(record, indent=2) + "\n")


if __name__ == "__main__":
    main()

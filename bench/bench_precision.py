"""fp32 against bf16, the machine and the project in one run: matmul peaks, then the training and
sampling steps of the tokenizer and the generator, interleaved.

Run (CPU):  .venv/bin/python bench/bench_precision.py [--threads 2] [--rounds 5] [--batch 16] [--json out.json]
Run (GPU):  .venv/bin/python bench/bench_precision.py --device cuda --batch 64 --generator-batch 256 \\
                --generators 512x12@64 512x12@128 --tokenizer-sizes 128 --compile --peak-tflops 989

- **The machine**: the best fp32 and bf16 GFLOP/s of n x n matrix products (n = 512 ... 2048 on the
  CPU, up to 8192 on a GPU); the largest bf16 figure is "the bf16 peak" every share below is of.
  ``--peak-tflops`` adds the share of a stated peak (the device's data-sheet bf16 dense figure).
- **Contenders**: the tokenizer's training step (L1 + VQ, AdamW; VQGAN and DM-VQGAN at 32 base
  channels, at each of ``--tokenizer-sizes``, default the bundled 64 px and 128 px); the generator's
  training step (loss, backward, AdamW, label conditioner) and sampling step (one denoiser pass
  under ``no_grad``) of each of ``--generators``: a bundle (``tour``, ``tour_wide``: the shipped
  networks) or ``WIDTHxDEPTH@SIZE`` (a fresh network of that width and depth, heads = width / 64,
  over the code grid of SIZE px images at f = 4, 512 codes).
- **Variants** of each: ``fp32`` and ``bf16`` as the trainer runs them now (Adam's fused kernel;
  ``precision: bf16`` is ``torch.autocast(device, dtype=torch.bfloat16)``, the quantizer's distances
  fp32 inside it; on the CPU the denoiser's :func:`~vqtouch.plugins.generator.denoiser.attend` takes
  its explicit form for bf16 training), and the training steps as they ran before: ``fp32 before``
  (per-tensor Adam) and, for the generator, ``bf16 autocast alone`` (per-tensor Adam, the fused
  attention kernel), so the levers' shares show; ``--compile`` adds ``bf16 compiled`` (the
  denoiser under ``torch.compile``, compile time reported apart) and ``--channels-last``
  ``bf16 channels-last`` (the tokenizer's networks and images in channels-last memory format).
- Every round times one call of every contender in a rotated order, so the machine's drift hits
  all alike; reported: the median ms per step, images per second, the median of the per-round
  ratios (paired), the step's matmul and convolution FLOPs (``torch.utils.flop_counter``, forward
  and backward) per second and its share of the bf16 peak; on a GPU the peak memory of each step.

Say the machine's load beside the figures: two torch jobs on two cores slow each other far more
than twice.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import json
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_dm_vqgan import build, counted_flops, matmul_peak_gflops, sync  # noqa: E402

TOKENIZER_VARIANTS = ("fp32 before", "fp32", "bf16")
GENERATOR_VARIANTS = ("fp32 before", "fp32", "bf16 autocast alone", "bf16")
SAMPLING_VARIANTS = ("fp32", "bf16")


def autocast(variant: str, device: torch.device) -> contextlib.AbstractContextManager:
    """What a component's ``precision`` does on ``device``."""
    if variant.startswith("bf16"):
        return torch.autocast(device.type, dtype=torch.bfloat16)
    return contextlib.nullcontext()


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


def tokenizer_steps(name: str, size: int, batch: int, device: torch.device, channels_last: bool) -> dict:
    """One tokenizer's training step in each variant (the same weights and images; ``bf16 channels-last``
    on a copy of the networks and images in channels-last memory format)."""
    config = {"name": name, **({"deformable_backend": "gather"} if name == "dm_vqgan" else {})}
    networks = build(config, size, batch, 32, device)

    def in_variant(variant: str) -> Callable:
        encoder, quantizer, _, images = networks
        if variant.endswith("channels-last"):
            encoder = copy.deepcopy(encoder).to(memory_format=torch.channels_last)
            quantizer, images = copy.deepcopy(quantizer), images.contiguous(memory_format=torch.channels_last)
        optimizer = adamw(list(encoder.parameters()) + list(quantizer.parameters()), variant)

        def step() -> None:
            with autocast(variant, device):
                latents = encoder.encode(images)
            output = quantizer(latents.float())  # fp32 inside, as TokenizerTask does
            with autocast(variant, device):
                reconstruction = encoder.decode(output.quantized_BDhw)
            loss = (reconstruction.float() - images).abs().mean() + output.loss
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()

        return step

    variants = TOKENIZER_VARIANTS + (("bf16 channels-last",) if channels_last else ())
    return {variant: in_variant(variant) for variant in variants}


def generator_networks(spec: str, device: torch.device) -> tuple:
    """(generator, label conditioner, number of classes) of a bundle name or ``WIDTHxDEPTH@SIZE``."""
    from vqtouch.core import BuildContext, load_plugins

    torch.manual_seed(0)
    host = load_plugins()
    if "x" not in spec:
        from vqtouch.plugins.generator import load_pipeline

        pipe = load_pipeline(f"pretrained:{spec}", host=host)
        return pipe.generator.to(device), pipe.conditioners[0].to(device), len(pipe.class_names)
    shape, size = spec.split("@")
    width, depth = (int(value) for value in shape.split("x"))
    context = BuildContext(image_size=int(size), num_classes=12, cond_dim=width, codebook_size=512)
    context = context.model_copy(update={"code_grid": int(size) // 4})
    model = {"name": "vq_diffusion", "width": width, "depth": depth, "heads": max(1, width // 64)}
    generator = host.build("generator", model, context).to(device)
    return generator, host.build("conditioner", {"name": "label"}, context).to(device), 12


def generator_steps(spec: str, batch: int, device: torch.device, compile_network: bool) -> tuple[dict, dict]:
    """The training step (each variant) and the sampling step (fp32, bf16) of a generator with its
    label conditioner."""
    generator, conditioner, classes = generator_networks(spec, device)
    height, width = generator.grid_hw
    codes_BHW = torch.randint(0, generator.num_codes, (batch, height, width), device=device)
    labels_B = torch.randint(0, classes, (batch,), device=device)
    params = [p for module in (generator, conditioner) for p in module.parameters()]
    eager = generator.network

    def train(variant: str) -> Callable:
        optimizer = adamw(params, variant)

        def step() -> None:
            generator.train()
            conditioner.train()
            generator.network = compiled if variant == "bf16 compiled" else eager
            try:
                with fused_attention_only(variant), autocast(variant, device):
                    loss, _ = generator.training_loss(codes_BHW, conditioner(labels_B))
                optimizer.zero_grad(set_to_none=True)
                loss.float().backward()
                optimizer.step()
            finally:
                generator.network = eager

        return step

    timestep_B = torch.full((batch,), generator.config.num_steps // 2, device=device)

    def sample(variant: str) -> Callable:
        @torch.no_grad()
        def step() -> None:
            generator.eval()
            conditioner.eval()
            with autocast(variant, device):
                condition = conditioner(labels_B)
                generator.network(
                    codes_BHW.flatten(1), timestep_B, condition=condition.tokens_BND, condition_grid=condition.grid_BDhw
                )

        return step

    variants = GENERATOR_VARIANTS + (("bf16 compiled",) if compile_network else ())
    compiled = torch.compile(eager) if compile_network else None
    return {v: train(v) for v in variants}, {p: sample(p) for p in SAMPLING_VARIANTS}


def contenders(args: argparse.Namespace, device: torch.device) -> dict[str, tuple[dict[str, Callable], int]]:
    """Every contender's steps by variant, with its images per step."""
    table: dict[str, tuple[dict[str, Callable], int]] = {}
    for name in args.tokenizers:
        for size in args.tokenizer_sizes:
            steps = tokenizer_steps(name, size, args.batch, device, args.channels_last)
            table[f"tokenizer train, {name}, {size} px"] = (steps, args.batch)
    batch = args.generator_batch or args.batch
    for spec in args.generators:
        train, sample = generator_steps(spec, batch, device, args.compile)
        table[f"generator train, {spec}"] = (train, batch)
        table[f"generator sampling step, {spec}"] = (sample, batch)
    return table


def warm_up(table: dict, device: torch.device) -> tuple[dict[str, float], dict[str, float]]:
    """One call of every (contender, variant) (allocator, autocast caches, kernels, compilation);
    returns the seconds of the slowest warm-up call per contender (the compile time, where one
    compiles) and each contender's peak memory in MB (GPU only)."""
    first, peak_mb = {}, {}
    for label, (steps, _) in table.items():
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        for variant, step in steps.items():
            tic = time.perf_counter()
            step()
            sync(device)
            first[f"{label} / {variant}"] = time.perf_counter() - tic
        if device.type == "cuda":
            peak_mb[label] = torch.cuda.max_memory_allocated(device) / 2**20
    return first, peak_mb


def measure(table: dict, rounds: int, device: torch.device) -> dict[str, dict[str, list[float]]]:
    """Seconds per call of every (contender, variant), ``rounds`` interleaved rounds in rotated order."""
    calls = [(label, variant) for label, (steps, _) in table.items() for variant in steps]
    seconds: dict[str, dict[str, list[float]]] = {label: {v: [] for v in steps} for label, (steps, _) in table.items()}
    for round_index in range(rounds):
        order = calls[round_index % len(calls) :] + calls[: round_index % len(calls)]
        for label, variant in order:
            sync(device)
            tic = time.perf_counter()
            table[label][0][variant]()
            sync(device)
            seconds[label][variant].append(time.perf_counter() - tic)
    return seconds


def paired_ratio(seconds: dict[str, list[float]], slow: str, fast: str) -> float:
    """The median of the per-round ``slow / fast`` time ratios."""
    return statistics.median(a / b for a, b in zip(seconds[slow], seconds[fast]))


def _ms(value: float | None) -> str:
    return "-" if value is None else f"{value * 1e3:.0f}"


def print_peaks(peaks: dict, sizes: list[int]) -> float:
    """The matmul table; returns the bf16 peak."""
    print("| matmul n | fp32 GFLOP/s | bf16 GFLOP/s | bf16 / fp32 |\n|---|---|---|---|")
    for size in sizes:
        fp32, bf16 = peaks[(size, "fp32")], peaks[(size, "bf16")]
        print(f"| {size} | {fp32:.0f} | {bf16:.0f} | {bf16 / fp32:.2f} |")
    return max(value for (_, name), value in peaks.items() if name == "bf16")


def print_steps(table: dict, seconds: dict, flops: dict, peak: float, stated: float | None, peak_mb: dict) -> list:
    """The per-step table (the training steps against how they ran before); returns its rows."""
    extra = (f" share of {stated:g} TFLOP/s |" if stated else "") + (" peak MB |" if peak_mb else "")
    print(
        "\n| step | fp32 before ms | fp32 ms | bf16 ms | before / bf16 (paired) | fp32 / bf16 (paired) | "
        f"bf16 img/s | GFLOP per step | bf16 GFLOP/s | share of the bf16 peak ({peak:.0f}) |{extra}\n"
        "|---|---|---|---|---|---|---|---|---|---|" + "---|" * extra.count("|")
    )
    rows = []
    for label, (_, images) in table.items():
        times = {variant: statistics.median(values) for variant, values in seconds[label].items()}
        before = times.get("fp32 before")
        achieved = flops[label] / times["bf16"] / 1e9
        row = {"step": label, **{f"{variant} s": value for variant, value in times.items()}}
        row.update(gflop=flops[label] / 1e9, gflops_bf16=achieved, peak_mb=peak_mb.get(label))
        row["fp32 / bf16"] = paired_ratio(seconds[label], "fp32", "bf16")
        row["before / bf16"] = paired_ratio(seconds[label], "fp32 before", "bf16") if before else None
        rows.append(row)
        speedup = "-" if before is None else f"{row['before / bf16']:.2f}"
        cells = [f"{achieved / (stated * 1e3):.1%}"] if stated else []
        cells += [f"{peak_mb[label]:.0f}"] if peak_mb else []
        print(
            f"| {label} | {_ms(before)} | {_ms(times['fp32'])} | {_ms(times['bf16'])} | {speedup} | "
            f"{row['fp32 / bf16']:.2f} | {images / times['bf16']:.1f} | {row['gflop']:.1f} | {achieved:.0f} | "
            f"{achieved / peak:.1%} |" + "".join(f" {cell} |" for cell in cells)
        )
    return rows


def print_levers(table: dict, seconds: dict) -> None:
    """What each lever gave each training step: every variant against ``fp32 before``."""
    for label, (steps, _) in table.items():
        if "train" in label:
            header = " | ".join(steps)
            print(f"\n| {label} | {header} |\n|---|" + "---|" * len(steps))
            ratios = {v: paired_ratio(seconds[label], "fp32 before", v) for v in steps}
            cells = [f"{_ms(statistics.median(seconds[label][v]))} ms ({ratios[v]:.2f}x)" for v in steps]
            print("| ms per step (against fp32 before) | " + " | ".join(cells) + " |")


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    parser.add_argument("--threads", type=int, default=2, help="CPU threads (default 2)")
    parser.add_argument("--rounds", type=int, default=5, help="interleaved timing rounds (default 5)")
    parser.add_argument("--batch", type=int, default=16, help="images per step (default 16)")
    parser.add_argument("--generator-batch", type=int, help="the generator's batch (default: --batch)")
    parser.add_argument("--tokenizers", nargs="*", default=["vqgan", "dm_vqgan"])
    parser.add_argument("--tokenizer-sizes", type=int, nargs="*", default=[64, 128])
    parser.add_argument(
        "--generators", nargs="*", default=["tour", "tour_wide"], help="bundle names or WIDTHxDEPTH@SIZE"
    )
    parser.add_argument("--compile", action="store_true", help="add the generator's bf16 step under torch.compile")
    parser.add_argument(
        "--channels-last", action="store_true", help="add the tokenizer's bf16 step in channels-last memory format"
    )
    parser.add_argument("--peak-tflops", type=float, help="a stated bf16 dense peak, for a second share column")
    parser.add_argument("--json", help="also write every measurement to this file")
    return parser.parse_args()


def main() -> None:
    args = parse_args()
    device = torch.device(args.device)
    torch.set_num_threads(args.threads)
    sizes = [512, 1024, 2048] + ([4096, 8192] if device.type == "cuda" else [])
    peaks = {
        (size, name): matmul_peak_gflops(device, size, repeats=8, dtype=dtype)
        for size in sizes
        for name, dtype in (("fp32", torch.float32), ("bf16", torch.bfloat16))
    }
    where = torch.cuda.get_device_name(device) if device.type == "cuda" else f"cpu, {torch.get_num_threads()} threads"
    print(f"torch {torch.__version__}, {where}, batch {args.batch} (generator {args.generator_batch or args.batch})")
    peak = print_peaks(peaks, sizes)
    table = contenders(args, device)
    flops = {label: counted_flops(steps["fp32"]) for label, (steps, _) in table.items()}
    first, peak_mb = warm_up(table, device)
    seconds = measure(table, args.rounds, device)
    rows = print_steps(table, seconds, flops, peak, args.peak_tflops, peak_mb)
    print_levers(table, seconds)
    if args.compile:
        compiled = {label: value for label, value in first.items() if label.endswith("compiled")}
        print("\nfirst call (compilation included): " + ", ".join(f"{k} {v:.0f} s" for k, v in compiled.items()))
    if args.json:
        record = {"peaks": {f"{size} {name}": value for (size, name), value in peaks.items()}, "rows": rows}
        Path(args.json).write_text(json.dumps(record, indent=2) + "\n")


if __name__ == "__main__":
    main()

"""Generator speed/quality trade: sampling cost and quality per knob, and training with the code cache.

Run:  .venv/bin/python bench/bench_generator.py --run RUN [--steps 100 50 25 10 5] [--samplers ...]
      [--batches 1 16] [--n 32] [--rounds 2] [--json out.json]

RUN is a run whose generator stage trained (``vqtouch train generator``).  Every sampling setting
(sampler x steps x guidance x precision x batch) runs in a fresh interpreter, so its peak memory
(max RSS; the interpreter's RSS after loading the pipeline is reported apart) is its own; the
settings are run ``--rounds`` times, interleaved (round 1 of every setting, then round 2, ...),
and the median throughput is reported, so machine drift hits every setting alike.  Generation,
timing and scoring are those of ``vqtouch tradeoff generator``
(:mod:`vqtouch.plugins.generator.tradeoff`, which measures every setting in one process and
draws the Pareto plot): the run's held-out conditions, the same seeds for every setting, each
image scored against the ground-truth tactile image of its own condition (SSIM, PSNR, contact
PSNR) and, with ``--fd``, ``fd_effnetlite0`` against the real held-out images and the accuracy
of a classifier trained on real images.  This script adds what one process cannot measure: each
setting's peak memory.  Cost ratios are against the first setting (the most steps) measured in
the same run.

``--train`` also measures generator training throughput (code grids per second) from cached
codes against the same step with the tokenizer's encoder run on the batch's images, which is what
training without the code cache would cost per step.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys

WORKER = r"""
import json, resource, sys, torch
args = json.loads(sys.argv[1])
torch.set_num_threads(args["threads"])
from vqtouch.core import load_plugins
from vqtouch.plugins.generator.tradeoff import load_tradeoff_bench
bench = load_tradeoff_bench(args["run"], load_plugins(), n=args["n"], batch_size=args["batch"], distribution=False)
setting = {key: args[key] for key in ("sampler", "steps", "guidance", "precision", "batch")}
loaded_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
bench.warm_up([setting])
seconds, images = bench.timed(setting)
peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
if args["fd"]:  # after the peak is read: the feature network's memory is not the sampler's
    bench.fit_distribution(args["feature_size"])
scores = bench.score(images)
print(json.dumps({"img_per_s": images.shape[0] / seconds, "seconds": seconds, "images": images.shape[0], **scores,
                  "finite": bool(torch.isfinite(images).all()), "loaded_mb": loaded_mb, "peak_mb": peak_mb}))
"""

TRAIN_WORKER = r"""
import json, sys, time, torch
args = json.loads(sys.argv[1])
torch.set_num_threads(args["threads"])
from vqtouch.core import Assembly, load_plugins
from vqtouch.plugins.runtime.run_dir import RunDir
from vqtouch.plugins.training.batches import collate_samples
from vqtouch.plugins.generator import load_pipeline
host = load_plugins()
pipe = load_pipeline(args["run"], host=host)
run = RunDir.open(args["run"])
dataset = Assembly(run.load_config(host), host).component("data.dataset")
batch = collate_samples([dataset[i] for i in range(args["batch"])])
conditioner, generator, tokenizer = pipe.conditioners[0], pipe.generator, pipe.tokenizer
generator.train(); conditioner.train()
params = [p for m in (generator, conditioner) for p in m.parameters() if p.requires_grad]
optimizer = torch.optim.AdamW(params, lr=1e-4)
with torch.no_grad():
    cached = tokenizer.encode_codes(batch["tactile"])
def step(encode):
    with torch.no_grad():
        codes = tokenizer.encode_codes(batch["tactile"]) if encode else cached
    condition = conditioner(conditioner.condition_of(batch))
    loss, _ = generator.training_loss(codes, condition)
    optimizer.zero_grad(set_to_none=True); loss.backward(); optimizer.step()
result = {}
for name, encode in (("cached", False), ("encoded", True), ("cached_again", False)):
    step(encode)
    times = []
    for _ in range(args["repeats"]):
        tic = time.perf_counter(); step(encode); times.append(time.perf_counter() - tic)
    result[name] = args["batch"] / statistics.median(times)
print(json.dumps(result))
""".replace("import json, sys, time, torch", "import json, statistics, sys, time, torch")


def run_worker(code: str, settings: dict) -> dict:
    """One measurement in a fresh interpreter (its own peak memory); the worker's last line is JSON."""
    completed = subprocess.run([sys.executable, "-c", code, json.dumps(settings)], capture_output=True, text=True)
    if completed.returncode != 0:
        raise SystemExit(f"setting {settings} failed:\n{completed.stderr[-3000:]}")
    return json.loads(completed.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", required=True, help="a run whose generator stage trained")
    parser.add_argument("--steps", type=int, nargs="+", default=[100, 50, 25, 10, 5])
    parser.add_argument("--samplers", nargs="+", default=["posterior", "purity", "confidence"])
    parser.add_argument("--guidance", type=float, nargs="+", default=[1.0, 3.0], help="1 is off")
    parser.add_argument("--precisions", nargs="+", default=["fp32", "bf16"])
    parser.add_argument("--batches", type=int, nargs="+", default=[16])
    parser.add_argument("--n", type=int, default=32, help="held-out conditions generated per setting")
    parser.add_argument("--rounds", type=int, default=2, help="interleaved repetitions (median reported)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument(
        "--fd",
        action="store_true",
        help="also score fd_effnetlite0 and the accuracy of a classifier trained on real images (slower)",
    )
    parser.add_argument(
        "--feature-size",
        type=int,
        help="EfficientNet-Lite0 input side for --fd (default: the run's fd_effnetlite0 metric's, else 224)",
    )
    parser.add_argument(
        "--only",
        choices=["steps", "grid"],
        default="steps",
        help="'steps': vary one knob at a time around the first sampler, guidance, precision and "
        "batch and the middle --steps value (posterior/25/unguided/fp32/16 by default); "
        "'grid': every combination",
    )
    parser.add_argument("--train", action="store_true", help="also measure training with and without the code cache")
    parser.add_argument("--json", help="write every measurement to this file")
    args = parser.parse_args()

    from vqtouch.plugins.generator.tradeoff import sweep_settings

    grid = args.only == "grid"
    # One knob at a time also measures batch 1 (the latency of a single image).
    batches = args.batches if grid else list(dict.fromkeys([*args.batches, 1]))
    settings = sweep_settings(
        steps=args.steps,
        samplers=args.samplers,
        guidance=args.guidance,
        precisions=args.precisions,
        grid=grid,
        batches=batches,
    )
    common = {"run": args.run, "n": args.n, "threads": args.threads, "fd": args.fd, "feature_size": args.feature_size}
    measured: list[list[dict]] = [[] for _ in settings]
    for round_index in range(args.rounds):
        for index, setting in enumerate(settings):
            measured[index].append(run_worker(WORKER, {**common, **setting}))
            print(f"round {round_index + 1}/{args.rounds}, setting {index + 1}/{len(settings)}", file=sys.stderr)
    reference = statistics.median(m["img_per_s"] for m in measured[0])
    header = (
        f"{'sampler':10s} {'steps':>5s} {'guid':>4s} {'prec':4s} {'batch':>5s} {'img/s':>7s} {'cost':>6s} "
        f"{'SSIM':>6s} {'PSNR':>6s}"
        + (f" {'FD':>7s} {'cls acc':>7s}" if args.fd else "")
        + f" {'peak MB':>8s} {'+load MB':>8s}"
    )
    print(
        f"run {args.run}; {measured[0][0]['images']} held-out conditions; {args.threads} threads; "
        f"median of {args.rounds} interleaved rounds; cost = time per image / that of the first row"
    )
    print(header)
    print("-" * len(header))
    rows = []
    for setting, results in zip(settings, measured):
        rate = statistics.median(r["img_per_s"] for r in results)
        row = {
            **setting,
            "img_per_s": rate,
            "cost": reference / rate,
            **{
                k: results[0][k]
                for k in (
                    "ssim",
                    "psnr",
                    "contact_psnr",
                    "fd_effnetlite0",
                    "classifier_accuracy",
                    "peak_mb",
                    "loaded_mb",
                    "finite",
                )
                if k in results[0]
            },
        }
        rows.append(row)
        accuracy = row.get("classifier_accuracy")
        fd = f" {row['fd_effnetlite0']:7.2f} {'-' if accuracy is None else f'{accuracy:.3f}':>7s}" if args.fd else ""
        print(
            f"{setting['sampler']:10s} {setting['steps']:5d} {setting['guidance']:4g} {setting['precision']:4s} "
            f"{setting['batch']:5d} {rate:7.2f} {row['cost']:5.2f}x {row['ssim']:6.4f} {row['psnr']:6.2f}{fd} "
            f"{row['peak_mb']:8.0f} {row['peak_mb'] - row['loaded_mb']:8.0f}"
        )
    train = None
    if args.train:
        train = run_worker(TRAIN_WORKER, {"run": args.run, "batch": 16, "repeats": 10, "threads": args.threads})
        print(
            f"\ntraining, batch 16: {train['cached']:.1f} code grids/s from the cache ({train['cached_again']:.1f} "
            f"measured again after), {train['encoded']:.1f}/s encoding each batch with the tokenizer: the cache is "
            f"{min(train['cached'], train['cached_again']) / train['encoded']:.2f}x faster per step"
        )
    if args.json:
        with open(args.json, "w", encoding="utf-8") as handle:
            json.dump({"settings": rows, "train": train, "rounds": args.rounds}, handle, indent=2)


if __name__ == "__main__":
    main()

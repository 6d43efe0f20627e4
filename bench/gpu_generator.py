"""The generator issue's GPU check: the bundle's generator recipe with more compute, a wider and
deeper generator at the same wall time, and the whole chain (tokenizer and generator) at 128 px.

Run on a machine with a GPU (about 8 minutes on one H200):

    python bench/gpu_generator.py --out OUT [--budget 470] [--batch 64] [--set KEY=VALUE ...]

``--set`` adds a config override to both 64 px generator jobs (and their probes), e.g. the levers
of docs/generation.md section 11 with a GPU's steps: ``--set data.dataset.num_samples=4000 --set
'generator.conditioners.1.grid_context=[1,2,4]'``.

Three jobs share the GPU, started together after a short probe that measures each 64 px
generator's training speed under that sharing:

- ``gen64``: the bundled ``tour`` generator's command (docs/guide.md, "Bundled pretrained
  checkpoints": width 128, depth 4, warm-up 200 steps, cosine decay, the bundled tokenizer's codes)
  with batch ``--batch`` and as many steps as its measured speed fits into the training window;
- ``gen64_wide``: the same with width 256 and depth 8, steps fitted the same way;
- ``tok128`` then ``gen128``: a DM-VQGAN tokenizer at 128 px with one more downsampling
  (f = 8, so the code grid stays 16 x 16 and the generator's cost stays that of 64 px), trained
  for a third of the window, then the same generator recipe on its codes for the rest.

Every job ends with ``vqtouch evaluate generation --run RUN --n N --classifier-on
reconstructions`` (all four conditioners, the default sampler, steps and per-conditioner guidance),
the same command that scores the bundle.  A job that outruns its window is stopped with SIGTERM,
which makes the trainer save the step reached; it is then scored at that step.  Every phase has
a deadline inside ``--budget`` seconds, so the results are packed into OUT before a caller's
time limit: ``results.tgz`` (configs, metrics, scores, sample sheets, logs) and each run's newest
weights (without optimiser state) as ``weights_NAME.tgz``.

``--dry`` runs the same plan with a few steps on the CPU (a check of this script, not a result).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tarfile
import threading
import time
from pathlib import Path

#: The bundled generator's recipe (``vqtouch pretrained list``), minus its step count and batch.
GENERATOR_RECIPE = [
    "--set", "data.dataset.seed=7",
    "--set", "generator.train.warmup_steps=200",
    "--set", "generator.train.lr_schedule=cosine",
    "--set", "generator.conditioners.1.input_size=128",
    "--set", "generator.conditioners.2.vocab_buckets=1024",
    "--set", "generator.num_samples=16",
    "--set", "generator.steps=25",
]  # fmt: skip
WIDE = ["--set", "generator.model.width=256", "--set", "generator.model.depth=8", "--set", "generator.model.heads=8"]
#: The bundled tokenizer's recipe at 128 px with one more downsampling level (f = 8).
TOKENIZER_128 = [
    "--set", "data.dataset.seed=7",
    "--set", "data.image_size=128",
    "--set", "tokenizer.autoencoder.channels=32",
    "--set", "tokenizer.autoencoder.channel_multipliers=[1,2,2,4]",
    "--set", "tokenizer.loss.perceptual=none",
]  # fmt: skip

START = time.monotonic()


def elapsed() -> float:
    return time.monotonic() - START


def log(message: str) -> None:
    print(f"[{elapsed():6.1f} s] {message}", flush=True)


def vqtouch(threads: int) -> list[str]:
    return [sys.executable, "-m", "vqtouch.core.cli", "--no-progress", "--threads", str(threads)]


def run(name: str, command: list[str], logs: Path, deadline: float, env: dict[str, str]) -> int:
    """Run ``command`` until it ends or ``deadline`` (seconds since start) passes; then SIGTERM, and
    SIGKILL 60 s later.  Output goes to ``logs/NAME.log``."""
    log(f"{name}: {' '.join(command[2:])}")
    with open(logs / f"{name}.log", "w") as out:
        process = subprocess.Popen(command, stdout=out, stderr=subprocess.STDOUT, env=env)
        while process.poll() is None:
            if elapsed() > deadline:
                log(f"{name}: deadline reached, SIGTERM (the trainer saves the step reached)")
                process.send_signal(signal.SIGTERM)
                try:
                    process.wait(timeout=60)
                except subprocess.TimeoutExpired:
                    process.kill()
                break
            time.sleep(0.5)
    code = process.wait()
    log(f"{name}: exit {code}")
    return code


def steps_per_second(run_dir: Path) -> float:
    """Training speed from the probe's log lines: steps between the first and last logged step over
    the time between them (file modification times are too coarse, so the watcher stamps them)."""
    stamps = json.loads((run_dir / "stamps.json").read_text())
    (t0, s0), (t1, s1) = stamps[0], stamps[-1]
    return (s1 - s0) / max(t1 - t0, 1e-6)


def watch_steps(run_dir: Path, stop: threading.Event) -> None:
    """Stamp each newly logged training step with the time it appeared (for ``steps_per_second``)."""
    stamps: list[tuple[float, int]] = []
    metrics = run_dir / "metrics.jsonl"
    while not stop.is_set():
        if metrics.exists():
            for line in metrics.read_text().splitlines():
                try:
                    record = json.loads(line)
                except json.JSONDecodeError:
                    continue
                if "loss" in record and (not stamps or record["step"] > stamps[-1][1]):
                    stamps.append((time.monotonic(), record["step"]))
        time.sleep(0.2)
    if len(stamps) >= 2:
        (run_dir / "stamps.json").write_text(json.dumps(stamps))


def overrides(args) -> list[str]:
    """The caller's ``--set`` overrides as command-line arguments of ``vqtouch train generator``."""
    return [part for value in args.set for part in ("--set", value)]


def probe(name: str, extra: list[str], args, work: Path, logs: Path, env) -> float:
    run_dir = work / f"probe_{name}"
    stop = threading.Event()
    watcher = threading.Thread(target=watch_steps, args=(run_dir, stop))
    watcher.start()
    command = vqtouch(args.threads) + [
        "train", "generator", "--scene", "tour", "--tokenizer", str(args.tokenizer), "--out", str(run_dir),
        "--overwrite", *GENERATOR_RECIPE, *overrides(args), *extra, "--set", f"data.batch_size={args.batch}",
        "--set", f"generator.train.steps={args.probe_steps}", "--set", "generator.train.log_every=10",
        "--set", "generator.num_samples=2", "--set", "generator.steps=2",
        "--set", f"generator.train.checkpoint_every={args.probe_steps}",
    ]  # fmt: skip
    code = run(f"probe_{name}", command, logs, args.probe_deadline, env)
    stop.set()
    watcher.join()
    if code != 0 or not (run_dir / "stamps.json").exists():
        raise SystemExit(f"probe {name} failed (exit {code}); see {logs / f'probe_{name}.log'}")
    rate = steps_per_second(run_dir)
    log(f"probe {name}: {rate:.2f} steps/s at batch {args.batch}")
    return rate


def generator_job(name, extra, steps, tokenizer, args, work, logs, env, train_deadline, results) -> None:
    run_dir = work / name
    command = vqtouch(args.threads) + [
        "train", "generator", "--scene", "tour", "--tokenizer", str(tokenizer), "--out", str(run_dir),
        "--overwrite", *GENERATOR_RECIPE, *overrides(args), *extra, "--set", f"data.batch_size={args.batch}",
        "--set", f"generator.train.steps={steps}", "--set", f"generator.train.checkpoint_every={max(steps // 4, 1)}",
    ]  # fmt: skip
    started = elapsed()
    code = run(name, command, logs, train_deadline, env)
    results[name] = {"steps_planned": steps, "train_exit": code, "train_seconds": round(elapsed() - started, 1)}
    evaluate(name, run_dir, args, logs, env, results)


def evaluate(name, run_dir, args, logs, env, results) -> None:
    command = vqtouch(args.threads) + [
        "evaluate", "generation", "--run", str(run_dir), "--n", str(args.eval_n),
        "--classifier-on", "reconstructions", "--out", str(run_dir / "eval"),
    ]  # fmt: skip
    started = elapsed()
    results[name]["eval_exit"] = run(f"{name}_eval", command, logs, args.budget - 25, env)
    results[name]["eval_seconds"] = round(elapsed() - started, 1)


def tokenizer_then_generator(rate, args, work, logs, env, train_end, results) -> None:
    tokenizer_dir = work / "tok128"
    tokenizer_window = (train_end - elapsed()) / 3
    command = vqtouch(args.threads) + [
        "train", "tokenizer", "--scene", "tour", "--out", str(tokenizer_dir), "--overwrite", *TOKENIZER_128,
        "--set", f"data.batch_size={args.tokenizer_batch}", "--set", "tokenizer.train.steps=1000000",
        "--set", "tokenizer.train.checkpoint_every=250", "--set", "tokenizer.train.log_every=50",
    ]  # fmt: skip
    started = elapsed()
    code = run("tok128", command, logs, elapsed() + tokenizer_window, env)
    results["tok128"] = {"train_exit": code, "train_seconds": round(elapsed() - started, 1)}
    # The 128 px generator sees the same 16 x 16 code grid; its conditions are rendered at 128 px.
    steps = max(int(rate * 0.8 * (train_end - elapsed())), 20)
    extra = ["--set", "data.image_size=128"]
    generator_job("gen128", extra, steps, tokenizer_dir, args, work, logs, env, train_end + 20, results)


#: The device tool brings back files of at most 16 MB.
PART_BYTES = 15_000_000


def half_precision(path: Path) -> None:
    """Store a checkpoint file's float32 tensors as float16, header kept (halves what travels back;
    the bundle ships float16 parameters the same way)."""
    import torch
    from safetensors import safe_open
    from safetensors.torch import save_file

    with safe_open(str(path), "pt") as handle:
        metadata = handle.metadata()
        tensors = {key: handle.get_tensor(key) for key in handle.keys()}
    halved = {k: v.half() if v.dtype == torch.float32 else v for k, v in tensors.items()}
    save_file(halved, str(path), metadata=metadata)


def split(path: Path, part_bytes: int) -> None:
    """Cut ``path`` into ``path.part0``, ``path.part1``, ... when it is larger than ``part_bytes``
    (join them with ``cat path.part* > path``)."""
    data = path.read_bytes()
    if len(data) <= part_bytes:
        return
    for index, begin in enumerate(range(0, len(data), part_bytes)):
        path.with_name(f"{path.name}.part{index}").write_bytes(data[begin : begin + part_bytes])
    path.unlink()


def newest_checkpoints(run_dir: Path) -> list[Path]:
    """The newest ``step-*`` folder of each checkpoint series in a run: ``checkpoints/step-*`` (a
    tokenizer run) and ``checkpoints/COMPONENT/step-*`` (a generator run)."""
    root = run_dir / "checkpoints"
    if not root.is_dir():
        return []
    series = [root, *(p for p in sorted(root.iterdir()) if p.is_dir() and not p.name.startswith("step-"))]
    return [sorted(folder.glob("step-*"))[-1] for folder in series if any(folder.glob("step-*"))]


def pack(work: Path, logs: Path, out: Path, results: dict) -> None:
    (logs / "results.json").write_text(json.dumps(results, indent=2))
    with tarfile.open(out / "results.tgz", "w:gz") as archive:
        archive.add(logs, arcname="logs")
        for run_dir in sorted(work.iterdir()):
            for path in sorted(run_dir.rglob("*")):
                wanted = path.suffix in {".json", ".jsonl", ".png", ".md"}
                if wanted and path.is_file() and "checkpoints" not in path.parts:
                    archive.add(path, arcname=str(path.relative_to(work)))
    for run_dir in sorted(work.iterdir()):
        newest = newest_checkpoints(run_dir)
        if run_dir.name.startswith("probe") or not newest:
            continue
        archive_path = out / f"weights_{run_dir.name}.tgz"
        with tarfile.open(archive_path, "w:gz") as archive:
            archive.add(run_dir / "config.json", arcname=f"{run_dir.name}/config.json")
            for folder in newest:
                for path in sorted(folder.iterdir()):
                    if path.name != "trainer_state.safetensors":
                        if not path.name.startswith("quantizer"):  # codes depend on the codebook's exact values
                            half_precision(path)
                        archive.add(path, arcname=f"{run_dir.name}/{path.relative_to(run_dir)}")
        split(archive_path, PART_BYTES)
    log("packed: " + ", ".join(f"{p.name} {p.stat().st_size / 1e6:.1f} MB" for p in sorted(out.iterdir())))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--work", type=Path, default=Path("/tmp/vqtouch_gpu"))
    parser.add_argument("--budget", type=float, default=470.0, help="seconds from start to packed results")
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--tokenizer-batch", type=int, default=16)
    parser.add_argument("--probe-steps", type=int, default=150)
    parser.add_argument("--probe-deadline", type=float, default=110.0)
    parser.add_argument("--eval-window", type=float, default=200.0, help="seconds kept for scoring at the end")
    parser.add_argument("--eval-n", type=int, default=64)
    parser.add_argument("--threads", type=int, default=5)
    parser.add_argument("--tokenizer", type=Path, default=Path("plugins/pretrained/weights/tour/tokenizer"))
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a config override for both 64 px generator jobs (repeatable)",
    )
    parser.add_argument("--dry", action="store_true", help="a few steps on the CPU: checks this script")
    args = parser.parse_args()
    env = dict(os.environ, VQTOUCH_NO_PROGRESS="1", PYTHONUNBUFFERED="1")
    if args.dry:
        env["CUDA_VISIBLE_DEVICES"] = ""
    args.out.mkdir(parents=True, exist_ok=True)
    logs = args.work / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    results: dict = {}
    import torch

    results["device"] = torch.cuda.get_device_name(0) if torch.cuda.is_available() and not args.dry else "cpu"
    log(f"device: {results['device']}; torch {torch.__version__}")

    rates: dict[str, float] = {}
    probes = [("gen64", []), ("gen64_wide", WIDE)]
    threads = [
        threading.Thread(target=lambda n=n, e=e: rates.__setitem__(n, probe(n, e, args, args.work, logs, env)))
        for n, e in probes
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    results["probe_steps_per_second"] = rates
    if len(rates) < 2:
        pack(args.work, logs, args.out, results)
        raise SystemExit("a probe failed; see results.tgz")

    train_end = args.budget - args.eval_window
    window = train_end - elapsed()
    shared = (args, args.work, logs, env)
    jobs = [
        threading.Thread(
            target=generator_job,
            args=("gen64", [], int(rates["gen64"] * window), args.tokenizer, *shared, train_end + 20, results),
        ),
        threading.Thread(
            target=generator_job,
            args=(
                "gen64_wide", WIDE, int(rates["gen64_wide"] * window), args.tokenizer, *shared, train_end + 20, results
            ),
        ),
        threading.Thread(target=tokenizer_then_generator, args=(rates["gen64"], *shared, train_end, results)),
    ]  # fmt: skip
    for job in jobs:
        job.start()
    for job in jobs:
        job.join()
    pack(args.work, logs, args.out, results)


if __name__ == "__main__":
    main()

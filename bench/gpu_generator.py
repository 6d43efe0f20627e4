"""The generator issue's GPU check: the bundled generator's recipe with a GPU's steps, a wider and
deeper generator at the same wall time, and the whole chain (tokenizer and generator) at 128 px.

Run on a machine with a GPU (about 8 minutes on one H200):

    python bench/gpu_generator.py --out OUT [--budget 500] [--batch 64] [--jobs gen64_wide,chain128]
                                  [--set KEY=VALUE ...]

The recipe is read from the bundle itself (``vqtouch pretrained list``: the ``--set`` overrides of
the command that trained its generator, and the sampling defaults set at export), less its step
count and batch, so this check follows the bundle when the bundle changes.  ``--set`` adds a config
override to the 64 px generator jobs (and their probes), e.g. ``--set data.dataset.num_samples=4000``
(more procedural scenes, against the wide model's overfitting).

The jobs (``--jobs``, comma-separated; all share the GPU):

- ``gen64``: the bundle's recipe with batch ``--batch`` and as many steps as its measured speed fits
  into the training window;
- ``gen64_wide``: the same with width 256 and depth 8, steps fitted the same way;
- ``chain128``: ``tok128``, a DM-VQGAN tokenizer at 128 px with one more downsampling (f = 8, so the
  code grid stays 16 x 16 and the generator's cost stays that of 64 px), trained from the start
  (beside the probes) for ``--tokenizer-share`` of the time to the end of training, then
  ``gen128``, the bundle's generator recipe on its codes for the rest.

The speed of each 64 px generator is measured first by a short probe under the same sharing.  Each
generator is then scored, one conditioner at a time, by ``vqtouch evaluate generation --run RUN
--conditioner I --n N --out RUN/eval_I`` (the default sampler, steps and per-conditioner guidance:
the command that scores the bundle): label and text with ``--classifier-on reconstructions``, touch
and vision with ``--no-distribution`` (their contact scores in a third of the time; their fd comes
from the weights brought back).  Label first; a conditioner scored before the deadline keeps its
result when a later one is cut off.  A job that outruns its window is stopped with SIGTERM, which
makes the trainer save the step reached; it is then scored at that step.  Every phase has a
deadline inside ``--budget`` seconds, so the results are packed into OUT before a caller's time
limit: ``results.tgz`` (configs, metrics, scores, sample sheets, logs) and ``weights_RUN.tgz`` per
run, split into 15 MB parts where larger (``cat weights_RUN.tgz.part* > weights_RUN.tgz``): the
newest step folder, generators' weights in float16, a tokenizer's exact, and the trainer state
without the optimiser, so that unpacked it is a run ``--run`` scores (not one that resumes).

``--dry`` runs the same plan with a few steps on the CPU (a check of this script, not a result).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import signal
import subprocess
import sys
import tarfile
import tempfile
import threading
import time
from pathlib import Path

#: Overrides of the bundle's generator command that this check sets itself.
OWN_KEYS = ("data.batch_size", "generator.train.steps", "generator.train.checkpoint_every", "generator.train.log_every")


def bundle_recipe(name: str = "tour") -> list[str]:
    """The arguments of the command that trained bundle ``name``'s generator: its shipped recipe file
    (``--config``) when it names one, and its ``--set`` values less those in ``OWN_KEYS``, plus the
    sampling defaults set at export (as ``generator.conditioner_guidance``)."""
    from vqtouch.plugins.pretrained.bundle import RECIPES, bundle_folder, describe_bundle

    facts = describe_bundle(bundle_folder(name))
    words = shlex.split(facts["generator_command"].split("#")[0])
    values = [words[i + 1] for i, word in enumerate(words[:-1]) if word == "--set"]
    recipe_file = facts["recipes"]["generator"]
    recipe = ["--config", str(RECIPES / recipe_file)] if recipe_file else []
    recipe += [part for value in values if value.split("=")[0] not in OWN_KEYS for part in ("--set", value)]
    guidance = facts["sampling_defaults"].get("conditioner_guidance")
    if guidance:
        recipe += ["--set", f"generator.conditioner_guidance={json.dumps(guidance, separators=(',', ':'))}"]
    return recipe


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
    return [sys.executable, "-m", "vqtouch.plugins.cli", "--no-progress", "--threads", str(threads)]


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


#: Speeds assumed when a probe fails (steps per second at batch 64 on a shared H200, below the
#: 18.7 and 13.3 measured for a lighter recipe); a job that outruns its window is stopped anyway.
FALLBACK_STEPS_PER_SECOND = {"gen64": 12.0, "gen64_wide": 8.0}


def probe(name: str, extra: list[str], args, work: Path, logs: Path, env) -> float:
    run_dir = work / f"probe_{name}"
    stop = threading.Event()
    watcher = threading.Thread(target=watch_steps, args=(run_dir, stop))
    watcher.start()
    command = vqtouch(args.threads) + [
        "train", "generator", "--scene", "tour", "--tokenizer", str(args.tokenizer), "--out", str(run_dir),
        "--overwrite", *args.recipe, *overrides(args), *extra, "--set", f"data.batch_size={args.batch}",
        "--set", f"generator.train.steps={args.probe_steps}", "--set", "generator.train.log_every=10",
        "--set", "generator.num_samples=2", "--set", "generator.steps=2",
        "--set", f"generator.train.checkpoint_every={args.probe_steps}",
    ]  # fmt: skip
    code = run(f"probe_{name}", command, logs, args.probe_deadline, env)
    stop.set()
    watcher.join()
    if code != 0 or not (run_dir / "stamps.json").exists():
        rate = FALLBACK_STEPS_PER_SECOND[name]
        log(f"probe {name} failed (exit {code}; see {logs / f'probe_{name}.log'}): {rate} steps/s assumed")
        return rate
    rate = steps_per_second(run_dir)
    log(f"probe {name}: {rate:.2f} steps/s at batch {args.batch}")
    return rate


def generator_job(name, extra, steps, tokenizer, args, work, logs, env, train_deadline, results) -> None:
    run_dir = work / name
    command = vqtouch(args.threads) + [
        "train", "generator", "--scene", "tour", "--tokenizer", str(tokenizer), "--out", str(run_dir),
        "--overwrite", *args.recipe, *extra, "--set", f"data.batch_size={args.batch}",
        "--set", f"generator.train.steps={steps}", "--set", f"generator.train.checkpoint_every={max(steps // 4, 1)}",
    ]  # fmt: skip
    started = elapsed()
    code = run(name, command, logs, train_deadline, env)
    results[name] = {"steps_planned": steps, "train_exit": code, "train_seconds": round(elapsed() - started, 1)}
    evaluate(name, run_dir, args, logs, env, results)


#: The order conditioners are scored in (the label's figure is the one furthest from its target).
SCORING_ORDER = (0, 3, 1, 2)
#: Conditioners scored by a classifier (label, text), which need the distribution scores.
CLASS_SCORED = {0, 2}


def evaluate(name, run_dir, args, logs, env, results) -> None:
    """Score each conditioner of ``run_dir`` into ``run_dir/eval_I`` until the deadline."""
    results[name]["eval"] = {}
    for index in SCORING_ORDER:
        if elapsed() > args.budget - 45:
            log(f"{name}: no time left to score conditioner {index}")
            break
        # The class-scored conditioners need the classifier (the distribution scores); the image
        # conditions' contact scores come without it in a third of the time (fd: from the weights).
        scoring = ["--classifier-on", "reconstructions"] if index in CLASS_SCORED else ["--no-distribution"]
        command = vqtouch(args.threads) + [
            "evaluate", "generation", "--run", str(run_dir), "--conditioner", str(index), "--n", str(args.eval_n),
            *scoring, "--out", str(run_dir / f"eval_{index}"),
        ]  # fmt: skip
        started = elapsed()
        code = run(f"{name}_eval_{index}", command, logs, args.budget - 25, env)
        results[name]["eval"][str(index)] = {"exit": code, "seconds": round(elapsed() - started, 1)}


def tokenizer_128(args, work, logs, env, deadline, results) -> Path:
    tokenizer_dir = work / "tok128"
    command = vqtouch(args.threads) + [
        "train", "tokenizer", "--scene", "tour", "--out", str(tokenizer_dir), "--overwrite", *TOKENIZER_128,
        "--set", f"data.batch_size={args.tokenizer_batch}", "--set", "tokenizer.train.steps=1000000",
        "--set", "tokenizer.train.checkpoint_every=100", "--set", "tokenizer.train.log_every=50",
    ]  # fmt: skip
    started = elapsed()
    code = run("tok128", command, logs, deadline, env)
    results["tok128"] = {"train_exit": code, "train_seconds": round(elapsed() - started, 1)}
    return tokenizer_dir


def generator_128(tokenizer_dir, rates, args, work, logs, env, train_end, results) -> None:
    # The 128 px generator sees the same 16 x 16 code grid; its conditions are rendered at 128 px.
    # It shares the GPU with the 64 px jobs as the probes did, less well: 0.8 of the probe's speed.
    startup = 30
    steps = max(
        int(rates.get("gen64", FALLBACK_STEPS_PER_SECOND["gen64"]) * 0.8 * (train_end - elapsed() - startup)), 20
    )
    extra = ["--set", "data.image_size=128"]
    generator_job("gen128", extra, steps, tokenizer_dir, args, work, logs, env, train_end + 20, results)


#: The device tool brings back files of at most 16 MB.
PART_BYTES = 15_000_000


def half_precision(source: Path, target: Path) -> None:
    """Write ``source``'s float32 tensors as float16 to ``target``, header kept (halves what travels
    back; the bundle ships float16 parameters the same way).  ``source`` is left as it is: a
    generator pins its tokenizer's files by digest, so changing them in place would break its scoring."""
    import torch
    from safetensors import safe_open
    from safetensors.torch import save_file

    with safe_open(str(source), "pt") as handle:
        metadata = handle.metadata()
        tensors = {key: handle.get_tensor(key) for key in handle.keys()}
    halved = {k: v.half() if v.dtype == torch.float32 else v for k, v in tensors.items()}
    save_file(halved, str(target), metadata=metadata)


def scoring_trainer_state(source: Path, target: Path) -> None:
    """Write ``source`` (a trainer state) to ``target`` without the optimiser's moments, which are most
    of its size.  The step folder stays complete, so the brought-back run can be scored with
    ``--run`` (the trainer state is what marks a folder complete; EMA weights are kept), but it
    cannot be resumed."""
    from safetensors import safe_open
    from safetensors.torch import save_file

    with safe_open(str(source), "pt") as handle:
        metadata = dict(handle.metadata())
        tensors = {key: handle.get_tensor(key) for key in handle.keys() if not key.startswith("optim.")}
    meta = json.loads(metadata["vqtouch.trainer"])
    metadata["vqtouch.trainer"] = json.dumps(meta | {"optimizers": {}, "history": []})
    save_file(tensors, str(target), metadata=metadata)


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
    """``results.tgz`` (logs, configs, metrics, scores, pictures) and ``weights_RUN.tgz`` per run: the
    newest step folder of each checkpoint series, a run that ``--run`` can score once unpacked."""
    (logs / "results.json").write_text(json.dumps(results, indent=2))
    with tarfile.open(out / "results.tgz", "w:gz") as archive:
        archive.add(logs, arcname="logs")
        for run_dir in sorted(work.iterdir()):
            for path in sorted(run_dir.rglob("*")):
                wanted = path.suffix in {".json", ".jsonl", ".png", ".md"}
                if wanted and path.is_file() and "checkpoints" not in path.parts:
                    archive.add(path, arcname=str(path.relative_to(work)))
    with tempfile.TemporaryDirectory() as staging:
        for run_dir in sorted(work.iterdir()):
            pack_weights(run_dir, Path(staging), out)
    log("packed: " + ", ".join(f"{p.name} {p.stat().st_size / 1e6:.1f} MB" for p in sorted(out.iterdir())))


def pack_weights(run_dir: Path, staging: Path, out: Path) -> None:
    """``out/weights_RUN.tgz`` from copies of ``run_dir``'s newest step folders made in ``staging``."""
    newest = newest_checkpoints(run_dir)
    if run_dir.name.startswith("probe") or not newest:
        return
    archive_path = out / f"weights_{run_dir.name}.tgz"
    with tarfile.open(archive_path, "w:gz") as archive:
        for name in ("config.json", "products.json", "metrics.jsonl"):
            if (run_dir / name).is_file():
                archive.add(run_dir / name, arcname=f"{run_dir.name}/{name}")
        for folder in newest:
            for path in sorted(folder.iterdir()):
                copy = staging / run_dir.name / path.relative_to(run_dir)
                copy.parent.mkdir(parents=True, exist_ok=True)
                if path.name == "trainer_state.safetensors":
                    scoring_trainer_state(path, copy)
                elif path.name.startswith(("autoencoder", "quantizer")):
                    # A tokenizer's files travel exact: its generators pin them by digest, and the
                    # codes depend on the codebook's exact values.
                    shutil.copyfile(path, copy)
                elif path.name.startswith("discriminator"):
                    continue  # training-only
                else:
                    half_precision(path, copy)
                archive.add(copy, arcname=f"{run_dir.name}/{path.relative_to(run_dir)}")
    split(archive_path, PART_BYTES)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--work", type=Path, default=Path("/tmp/vqtouch_gpu"))
    parser.add_argument("--budget", type=float, default=500.0, help="seconds from start to packed results")
    parser.add_argument("--jobs", default="gen64_wide,chain128", help="comma-separated: gen64, gen64_wide, chain128")
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--tokenizer-batch", type=int, default=16)
    parser.add_argument("--tokenizer-share", type=float, default=0.5, help="of the time to the end of training")
    parser.add_argument("--probe-steps", type=int, default=80)
    parser.add_argument("--probe-deadline", type=float, default=100.0)
    parser.add_argument("--eval-window", type=float, default=190.0, help="seconds kept for scoring at the end")
    parser.add_argument("--eval-n", type=int, default=64)
    parser.add_argument("--threads", type=int, default=5)
    parser.add_argument("--tokenizer", type=Path, default=Path("plugins/pretrained/weights/tour/tokenizer"))
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a config override for the 64 px generator jobs (repeatable)",
    )
    parser.add_argument("--dry", action="store_true", help="a few steps on the CPU: checks this script")
    args = parser.parse_args()
    jobs = set(args.jobs.split(","))
    unknown = jobs - {"gen64", "gen64_wide", "chain128"}
    if unknown:
        parser.error(f"--jobs: unknown {', '.join(sorted(unknown))}; choose from gen64, gen64_wide, chain128")
    args.recipe = bundle_recipe()
    env = dict(os.environ, VQTOUCH_NO_PROGRESS="1", PYTHONUNBUFFERED="1")
    if args.dry:
        env["CUDA_VISIBLE_DEVICES"] = ""
    args.out.mkdir(parents=True, exist_ok=True)
    logs = args.work / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    import torch

    results: dict = {"recipe": args.recipe, "jobs": sorted(jobs), "overrides": args.set}
    results["device"] = torch.cuda.get_device_name(0) if torch.cuda.is_available() and not args.dry else "cpu"
    log(f"device: {results['device']}; torch {torch.__version__}; recipe {' '.join(args.recipe)}")
    train_end = args.budget - args.eval_window
    shared = (args, args.work, logs, env)
    rates: dict[str, float] = {}

    # The 128 px tokenizer needs no probe: it starts at once, beside the probes.
    chain: list[threading.Thread] = []
    if "chain128" in jobs:
        tokenizer_deadline = args.tokenizer_share * train_end

        def chain128() -> None:
            tokenizer_dir = tokenizer_128(*shared, tokenizer_deadline, results)
            generator_128(tokenizer_dir, rates, *shared, train_end, results)

        chain.append(threading.Thread(target=chain128))
        chain[0].start()

    wanted = {"gen64"} if "chain128" in jobs else set()  # gen128's speed is read off gen64's probe
    probes = [(n, e) for n, e in (("gen64", []), ("gen64_wide", WIDE)) if n in jobs | wanted]
    threads = [threading.Thread(target=lambda n=n, e=e: rates.__setitem__(n, probe(n, e, *shared))) for n, e in probes]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    results["probe_steps_per_second"] = dict(rates)

    window = train_end - elapsed()
    workers = [
        threading.Thread(
            target=generator_job,
            args=(
                name,
                [*overrides(args), *extra],
                int(rates[name] * window),
                args.tokenizer,
                *shared,
                train_end + 20,
                results,
            ),
        )
        for name, extra in (("gen64", []), ("gen64_wide", WIDE))
        if name in jobs
    ]
    for worker in workers:
        worker.start()
    for worker in workers + chain:
        worker.join()
    pack(args.work, logs, args.out, results)


if __name__ == "__main__":
    main()

"""Fault cases, replayed through the ``vqtouch`` command line: for each case, the command,
its exit status and the last line it wrote to stderr (or what it left on disk).  Run it on two
checkouts to compare before and after a fix::

    .venv/bin/python bench/fault_cases.py [--keep DIR]

Everything runs on tiny models (a 32 px tokenizer trained 2 steps, a generator 6 steps) in a temporary
folder, one command at a time (about 3 minutes on 2 CPU cores).  Cases 15 (a full disk) and 16 (a
read-only run, which root may write to anyway) need a fault that a subprocess cannot be given; their
tests (tests/test_faults_generation.py) inject it in-process.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

VQTOUCH = [sys.executable, "-m", "vqtouch.plugins.cli"]
ENV = {**os.environ, "VQTOUCH_NO_PROGRESS": "1", "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")}
TOKENIZER = [
    "--scene", "reconstruction",
    "--set", "tokenizer.autoencoder.name=vqgan", "--set", "tokenizer.autoencoder.channels=16",
    "--set", "tokenizer.autoencoder.norm_groups=8", "--set", "tokenizer.autoencoder.channel_multipliers=[1,2]",
    "--set", "tokenizer.autoencoder.z_channels=16", "--set", "tokenizer.autoencoder.embed_dim=8",
    "--set", "tokenizer.quantizer.codebook_size=32", "--set", "data.image_size=32", "--set", "data.batch_size=4",
    "--set", "data.dataset.num_samples=16", "--set", "tokenizer.train.steps=2",
    "--set", "tokenizer.loss.perceptual=none", "--set", "tokenizer.discriminator=null",
]  # fmt: skip
GENERATOR = [
    "--scene", "label-to-touch",
    "--set", "generator.model.depth=1", "--set", "generator.model.width=32", "--set", "generator.model.num_steps=20",
    "--set", "generator.train.steps=6", "--set", "generator.train.checkpoint_every=3",
    "--set", "generator.num_samples=4", "--set", "generator.steps=4", "--set", "data.batch_size=4",
    "--set", "data.dataset.num_samples=24", "--set", "data.val_fraction=0.25",
]  # fmt: skip


def vqtouch(*args: str, cwd: Path | None = None, timeout: float = 300) -> tuple[int, str]:
    """Exit status and the last stderr line of ``vqtouch ARGS``."""
    try:
        done = subprocess.run(
            [*VQTOUCH, "--no-progress", *args], capture_output=True, text=True, env=ENV, cwd=cwd, timeout=timeout
        )
    except subprocess.TimeoutExpired:
        return -1, f"(still running after {timeout:.0f} s; stopped)"
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    return done.returncode, (lines[-1] if lines else "(no message)")[:400]


def poison(path: Path) -> None:
    """Every floating tensor of a safetensors file set to NaN, header kept."""
    import torch
    from safetensors import safe_open
    from safetensors.torch import save_file

    with safe_open(str(path), framework="pt") as handle:
        header = handle.metadata()
        tensors = {key: handle.get_tensor(key) for key in handle.keys()}
    nan = {k: torch.full_like(v, float("nan")) if v.is_floating_point() else v for k, v in tensors.items()}
    save_file(nan, str(path), metadata=header)


def files(folder: Path) -> int:
    return sum(1 for path in folder.rglob("*") if path.is_file()) if folder.exists() else 0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keep", help="work in this folder and keep it (default: a temporary one)")
    args = parser.parse_args()
    root = Path(args.keep or tempfile.mkdtemp(prefix="vqtouch-faults-"))
    root.mkdir(parents=True, exist_ok=True)
    tok, gen = root / "tok", root / "gen"
    for path in (tok, gen):
        shutil.rmtree(path, ignore_errors=True)
    assert vqtouch("train", "tokenizer", "--out", str(tok), *TOKENIZER)[0] == 0
    assert vqtouch("train", "generator", "--out", str(gen), "--tokenizer", str(tok), *GENERATOR)[0] == 0
    results: list[tuple[str, int, str]] = []

    def case(name: str, status: int, line: str) -> None:
        results.append((name, status, line))
        print(f"{name}\n  exit {status}: {line}", flush=True)

    # 1. the input as output
    before = files(tok)
    status, line = vqtouch("train", "generator", "--tokenizer", str(tok), "--out", str(tok), "--overwrite", *GENERATOR)
    case(
        "1 train generator --tokenizer TOK --out TOK --overwrite",
        status,
        f"{line} [TOK files {before} -> {files(tok)}]",
    )
    shutil.rmtree(tok, ignore_errors=True)
    assert vqtouch("train", "tokenizer", "--out", str(tok), *TOKENIZER)[0] == 0
    shutil.rmtree(gen, ignore_errors=True)
    assert vqtouch("train", "generator", "--out", str(gen), "--tokenizer", str(tok), *GENERATOR)[0] == 0

    # 2. the tokenizer retrained under a generator
    tok2, gen2 = root / "tok2", root / "gen2"
    shutil.rmtree(tok2, ignore_errors=True), shutil.rmtree(gen2, ignore_errors=True)
    vqtouch("train", "tokenizer", "--out", str(tok2), *TOKENIZER)
    vqtouch("train", "generator", "--out", str(gen2), "--tokenizer", str(tok2), *GENERATOR)
    vqtouch("train", "tokenizer", "--out", str(tok2), "--overwrite", "--set", "seed=7", *TOKENIZER)
    out = root / "out2"
    shutil.rmtree(out, ignore_errors=True)
    case(
        "2 generate after the tokenizer was retrained",
        *vqtouch("generate", "--run", str(gen2), "--label", "0", "--out", str(out)),
    )
    vqtouch(
        "train",
        "tokenizer",
        "--out",
        str(tok2),
        "--overwrite",
        "--set",
        "tokenizer.quantizer.codebook_size=16",
        *TOKENIZER,
    )
    shutil.rmtree(out, ignore_errors=True)
    case(
        "2 ... retrained with another codebook size",
        *vqtouch("generate", "--run", str(gen2), "--label", "0", "--out", str(out)),
    )

    # 3. NaN weights
    nan_gen = root / "gen_nan"
    shutil.rmtree(nan_gen, ignore_errors=True)
    shutil.copytree(gen, nan_gen)
    poison(sorted((nan_gen / "checkpoints" / "generator").glob("step-*"))[-1] / "generator.safetensors")
    shutil.rmtree(root / "out3", ignore_errors=True)
    case(
        "3 generate with NaN generator weights",
        *vqtouch("generate", "--run", str(nan_gen), "--label", "0", "--out", str(root / "out3")),
    )
    case(
        "3 evaluate generation with NaN weights",
        *vqtouch("evaluate", "generation", "--run", str(nan_gen), "--n", "2", "--steps", "2"),
    )
    bundles = root / "bundles"
    shutil.rmtree(bundles, ignore_errors=True)
    status, line = vqtouch(
        "pretrained", "export", "--run", str(nan_gen), "--name", "nan", "--root", str(bundles), "--precision", "fp32"
    )
    case(
        "3 pretrained export --precision fp32 of NaN weights",
        status,
        f"{line} [bundle folder left: {(bundles / 'nan').exists()}]",
    )

    # 4. generate --out reused
    out4 = root / "out4"
    shutil.rmtree(out4, ignore_errors=True)
    vqtouch("generate", "--run", str(gen), "--label", "0", "--n", "4", "--out", str(out4))
    status, line = vqtouch("generate", "--run", str(gen), "--label", "0", "--n", "2", "--out", str(out4))
    samples = len(list(out4.glob("sample_*.png")))
    case("4 generate --n 2 into a folder holding 4 samples", status, f"{line} [samples there: {samples}]")

    # 5. a huge --n
    start = time.perf_counter()
    status, line = vqtouch(
        "generate", "--run", str(gen), "--label", "0", "--n", "1000000000", "--out", str(root / "out5"), timeout=60
    )
    case("5 generate --n 1000000000", status, f"{line} [{time.perf_counter() - start:.0f} s]")
    shutil.rmtree(root / "out5", ignore_errors=True)

    # 6. the wrong kind of run
    status, line = vqtouch("train", "tokenizer", "--resume", str(gen))
    case("6 train tokenizer --resume GENRUN", status, line)
    before = files(tok)
    status, line = vqtouch("train", "generator", "--resume", str(tok))
    case("6 train generator --resume TOKRUN", status, f"{line} [TOK files {before} -> {files(tok)}]")

    # 7. SIGTERM during setup
    run7 = root / "run7"
    shutil.rmtree(run7, ignore_errors=True)
    process = subprocess.Popen(
        [*VQTOUCH, "--no-progress", "train", "tokenizer", "--out", str(run7), *TOKENIZER],
        stderr=subprocess.PIPE,
        text=True,
        env=ENV,
    )
    deadline = time.time() + 60
    while not (run7 / "config.json").exists() and time.time() < deadline:
        time.sleep(0.01)
    process.send_signal(signal.SIGTERM)
    err = [line for line in process.communicate()[1].splitlines() if line.strip()]
    case(
        "7 SIGTERM once the run folder exists (before the first step)",
        process.returncode,
        (err[-1] if err else "(no message)")[:300],
    )
    status, line = vqtouch("train", "tokenizer", "--resume", str(run7))
    case("7 ... then --resume", status, f"{line} [env.json: {(run7 / 'env.json').is_file()}]")

    # 8-10, 12. numbers
    for label, argv in [
        ("8 generate --guidance nan", ["generate", "--run", str(gen), "--label", "0", "--guidance", "nan"]),
        ("8 generate --truncation=-0.5", ["generate", "--run", str(gen), "--label", "0", "--truncation=-0.5"]),
        (
            "9 generate --seed 99999999999999999999",
            ["generate", "--run", str(gen), "--label", "0", "--seed", "99999999999999999999"],
        ),
        (
            "12 cluster --threshold nan",
            ["cluster", "--run", str(tok), "--sensors", "gelsight", "digit", "--threshold", "nan"],
        ),
        (
            "12 adapt --learning-rate nan",
            ["adapt", "--run", str(tok), "--images", "gelsight", "--learning-rate", "nan"],
        ),
    ]:
        shutil.rmtree(root / "outn", ignore_errors=True)
        case(label, *vqtouch(*argv, "--out", str(root / "outn")))
    shutil.rmtree(root / "run9", ignore_errors=True)
    status, line = vqtouch(
        "train", "tokenizer", "--out", str(root / "run9"), *TOKENIZER, "--set", "seed=9223372036854775807"
    )
    case("9 train tokenizer --set seed=9223372036854775807", status, line)
    shutil.rmtree(root / "run10", ignore_errors=True)
    status, line = vqtouch(
        "train",
        "generator",
        "--out",
        str(root / "run10"),
        *TOKENIZER,
        *GENERATOR,
        "--set",
        "generator.model.num_steps=100",
        "--set",
        "generator.steps=200",
    )
    case(
        "10 train generator --set generator.steps=200 (100 diffusion steps)",
        status,
        f"{line} [checkpoints written: {files(root / 'run10' / 'checkpoints')}]",
    )

    # 11. reconstruct with NaN weights
    nan_tok = root / "tok_nan"
    shutil.rmtree(nan_tok, ignore_errors=True)
    shutil.copytree(tok, nan_tok)
    poison(sorted((nan_tok / "checkpoints").glob("step-*"))[-1] / "autoencoder.safetensors")
    case(
        "11 reconstruct with NaN tokenizer weights",
        *vqtouch("reconstruct", "--run", str(nan_tok), "--real-frames", "gelsight", "--out", str(root / "out11")),
    )

    # 13. a sensor listed twice
    shutil.rmtree(root / "fam13", ignore_errors=True)
    case(
        "13 cluster --sensors gelsight gelsight digit",
        *vqtouch(
            "cluster",
            "--run",
            str(tok),
            "--image-size",
            "32",
            "--images",
            "8",
            "--sensors",
            "gelsight",
            "gelsight",
            "digit",
            "--out",
            str(root / "fam13"),
        ),
    )

    # 14. greyscale images
    from PIL import Image

    grey = root / "grey"
    shutil.rmtree(grey, ignore_errors=True)
    grey.mkdir()
    for index in range(4):
        Image.new("L", (32, 32), color=40 * index).save(grey / f"g{index}.png")
    case(
        "14 cluster with a folder of greyscale images",
        *vqtouch(
            "cluster",
            "--run",
            str(tok),
            "--image-size",
            "32",
            "--images",
            "4",
            "--sensors",
            str(grey),
            "gelsight",
            "--out",
            str(root / "fam14"),
        ),
    )

    # 17. families fitted from another working directory
    here = root / "here"
    shutil.rmtree(here, ignore_errors=True)
    here.mkdir()
    vqtouch(
        "cluster",
        "--run",
        os.path.relpath(tok, here),
        "--image-size",
        "32",
        "--images",
        "8",
        "--sensors",
        "gelsight",
        "digit",
        json.dumps({"name": "digit", "variant": {"seed": 2}}),
        "--out",
        "fam",
        cwd=here,
    )
    shutil.rmtree(root / "adapted17", ignore_errors=True)
    case(
        "17 adapt --families from another directory",
        *vqtouch(
            "adapt",
            "--run",
            str(tok),
            "--families",
            str(here / "fam"),
            "--images",
            "gelsight",
            "--shots",
            "4",
            "--steps",
            "1",
            "--eval-images",
            "4",
            "--batch-size",
            "4",
            "--threshold",
            "10",
            "--out",
            str(root / "adapted17"),
            cwd=root,
        ),
    )

    # 18. a run folder without its config.json
    run18 = root / "run18"
    shutil.rmtree(run18, ignore_errors=True)
    vqtouch("train", "tokenizer", "--out", str(run18), *TOKENIZER)
    (run18 / "config.json").unlink()
    case(
        "18 train into a run folder without config.json",
        *vqtouch("train", "tokenizer", "--out", str(run18), *TOKENIZER),
    )
    case("18 ... then --resume it", *vqtouch("train", "tokenizer", "--resume", str(run18)))

    (root / "fault_cases.json").write_text(json.dumps(results, indent=2) + "\n")
    print(f"-> {root / 'fault_cases.json'}")
    if not args.keep:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()

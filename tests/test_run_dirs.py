"""A run directory belongs to one run: creating into a used folder is refused (or
emptied with --overwrite), one process writes a run at a time (an advisory file lock), and every
reader of a run checks that the checkpoint it picks was made with the run's own config."""

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import textwrap

import pytest

from vqtouch.core import Assembly, load_plugins, read_metadata
from vqtouch.plugins.runtime.execution import run_stage
from vqtouch.plugins.runtime.run_dir import RunDir
from vqtouch.plugins.cli.app import main

HOST = load_plugins(autoload=False)
TINY = [
    "tokenizer.autoencoder.channels=16",
    "tokenizer.autoencoder.norm_groups=8",
    "tokenizer.autoencoder.channel_multipliers=[1,2]",
    "tokenizer.autoencoder.z_channels=16",
    "tokenizer.autoencoder.embed_dim=8",
    "data.image_size=32",
    "data.batch_size=4",
    "data.dataset.num_samples=24",
    "tokenizer.train.steps=4",
    "tokenizer.train.log_every=1",
    "tokenizer.train.checkpoint_every=2",
    "tokenizer.loss.perceptual=none",
    'tokenizer.discriminator={"name": "patchgan"}',  # resume must restore its weights and optimizer too
    "tokenizer.loss.disc_start=2",
    'metrics=[{"name": "psnr"}]',
]


def train_args(out, codebook_size=32, *extra):
    """`vqtouch train tokenizer --out OUT` with a tiny model and the given codebook size."""
    args = ["--no-progress", "train", "tokenizer", "--out", str(out), *extra]
    for override in [*TINY, f"tokenizer.quantizer.codebook_size={codebook_size}"]:
        args += ["--set", override]
    return args


def codebook_in_header(folder):
    return json.loads(read_metadata(folder / "quantizer.safetensors")["vqtouch.config"])["codebook_size"]


def error_line(capsys):
    """The whole of stderr, which must be one line."""
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1, lines
    return lines[0]


def test_training_into_an_older_run_is_refused_and_overwrite_replaces_it(tmp_path, capsys):
    run = tmp_path / "run"
    assert main(train_args(run, 64)) == 0
    metrics_before = (run / "metrics.jsonl").read_text()
    capsys.readouterr()
    assert main(train_args(run, 128)) == 2
    assert error_line(capsys) == (
        f"vqtouch: error: {run} already holds a run; continue it with --resume {run}, "
        "start it afresh with --overwrite, or choose another --out"
    )
    assert json.loads((run / "config.json").read_text())["tokenizer"]["quantizer"]["codebook_size"] == 64
    assert (run / "metrics.jsonl").read_text() == metrics_before

    assert main(train_args(run, 128, "--overwrite")) == 0
    assert json.loads((run / "config.json").read_text())["tokenizer"]["quantizer"]["codebook_size"] == 128
    lines = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [line["step"] for line in lines if "val_loss" not in line] == [1, 2, 3, 4]  # the new run's lines only
    assert [line["step"] for line in lines if "val_loss" in line] == [2, 4]  # one score per checkpoint
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["step-00000002", "step-00000004"]
    assert {codebook_in_header(run / "checkpoints" / name) for name in ("step-00000002", "step-00000004")} == {128}
    assert main(["train", "tokenizer", "--resume", str(run), "--overwrite"]) == 2
    assert error_line(capsys) == (
        "vqtouch: error: --overwrite starts a new run and --resume continues one; give one of them"
    )


def test_overwrite_will_not_wipe_a_folder_that_is_not_a_run(tmp_path, capsys):
    folder = tmp_path / "thesis"
    folder.mkdir()
    (folder / "chapter1.tex").write_text("precious")
    assert main(train_args(folder, 32, "--overwrite")) == 2
    assert error_line(capsys) == (
        f"vqtouch: error: {folder} is not empty and is not a run directory (no "
        "config.json); choose an empty or new --out (--overwrite only empties run "
        "directories)"
    )
    assert [p.name for p in folder.iterdir()] == ["chapter1.tex"]


def test_every_reader_refuses_a_folder_that_mixes_two_runs(tmp_path, capsys):
    """A folder that mixes two runs: this run's config says 64 codes, and an older run's checkpoint (128 codes)
    is the newest step folder."""
    run, other = tmp_path / "run", tmp_path / "other"
    assert main(train_args(run, 64)) == 0
    assert main(train_args(other, 128)) == 0
    shutil.copytree(other / "checkpoints" / "step-00000004", run / "checkpoints" / "step-00000008")
    mixed = run / "checkpoints" / "step-00000008" / "quantizer.safetensors"
    message = (
        f"{mixed} was made with quantizer 'vq' {{\"codebook_size\": 128}} but the run's config.json says "
        'tokenizer.quantizer {"codebook_size": 64}; this folder mixes two runs: pick one of this run\'s own '
        "steps with --step, or retrain into an empty --out"
    )
    capsys.readouterr()
    assert main(["reconstruct", "--run", str(run), "--real-frames", "gelsight", "--out", str(tmp_path / "r")]) == 2
    assert error_line(capsys) == f"vqtouch: error: {message}"
    assert (
        main(["reconstruct", "--run", str(mixed.parent), "--real-frames", "gelsight", "--out", str(tmp_path / "r")])
        == 2
    )  # the step folder itself, inside the run
    assert error_line(capsys) == f"vqtouch: error: {message}"
    assert main(["evaluate", "reconstruction", "--run", str(run)]) == 2
    assert error_line(capsys) == f"vqtouch: error: {message}"
    assert main(["--no-progress", "train", "tokenizer", "--resume", str(run)]) == 2
    assert error_line(capsys) == f"vqtouch: error: stage 'tokenizer' failed: {message}"
    reader = RunDir.open(run)
    outcome = run_stage("reconstruct", Assembly(reader.load_config(HOST), HOST), reader)
    assert outcome.describe() == f"failed: {message}"
    # This run's own step is still readable.
    assert main(["evaluate", "reconstruction", "--run", str(run), "--step", "4"]) == 0
    assert json.loads(capsys.readouterr().out)["checkpoint"] == str(run / "checkpoints" / "step-00000004")


def test_two_trainings_started_into_one_directory_at_once(tmp_path):
    """Two real processes: exactly one trains, the other is refused naming the first one's pid."""
    run = tmp_path / "run"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    processes = [
        subprocess.Popen(
            [sys.executable, "-m", "vqtouch.plugins.cli", *train_args(run, size)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )
        for size in (64, 128)
    ]
    results = [(p.pid, *p.communicate(timeout=300), p.returncode) for p in processes]
    assert sorted(code for *_, code in results) == [0, 2], [r[2][-2000:] for r in results]
    (winner_pid, *_), (_, _, refused_err, _) = sorted(results, key=lambda r: r[3])
    assert refused_err.strip().splitlines() == [
        f"vqtouch: error: {run} is in use by another vqtouch process (pid {winner_pid}); wait for it to finish or "
        "stop it, or choose another --out"
    ]
    size = json.loads((run / "config.json").read_text())["tokenizer"]["quantizer"]["codebook_size"]
    assert {codebook_in_header(folder) for folder in (run / "checkpoints").iterdir()} == {size}


HOLD_LOCK = textwrap.dedent("""
    import sys
    from vqtouch.core import load_plugins, resolve_config
    from vqtouch.plugins.runtime.run_dir import RunDir

    host = load_plugins(autoload=False)
    config = resolve_config("reconstruction", overrides=sys.argv[2:], host=host)
    run = RunDir.create(config, host=host, path=sys.argv[1])
    print("locked", flush=True)
    sys.stdin.readline()
    run.close()
    print("released", flush=True)
    sys.stdin.readline()
""")


@pytest.mark.parametrize("ending", ["normal exit", "SIGKILL"])
def test_a_second_writer_is_refused_while_the_first_lives(tmp_path, capsys, ending):
    run = tmp_path / "run"
    # Tiny, so that a --resume which wrongly got through trains for a second, not for an hour.
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLD_LOCK, str(run), *TINY, "tokenizer.quantizer.codebook_size=64"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "locked"
        busy = (
            f"vqtouch: error: {run} is in use by another vqtouch process (pid {holder.pid}); wait for it to "
            "finish or stop it, or choose another --out"
        )
        assert main(["train", "tokenizer", "--resume", str(run)]) == 2
        assert error_line(capsys) == busy
        assert main(train_args(run, 128, "--overwrite")) == 2
        assert error_line(capsys) == busy
        assert (run / "config.json").is_file()  # the live run was not wiped
        assert RunDir.open(run).load_config(HOST).tokenizer.quantizer.codebook_size == 64  # readers may read
        if ending == "SIGKILL":
            os.kill(holder.pid, signal.SIGKILL)
            holder.wait(timeout=30)
        else:
            holder.stdin.write("\n")
            holder.stdin.flush()
            assert holder.stdout.readline().strip() == "released"  # released explicitly, still running
        with RunDir.open(run, for_writing=True) as reopened:
            assert (reopened.path / ".vqtouch.lock").read_text().strip() == str(os.getpid())
    finally:
        holder.kill()
        holder.wait(timeout=30)


def test_demo_refuses_a_used_out_and_overwrite_replaces_it(tmp_path, capsys):
    out = tmp_path / "run"
    demo = [
        "--no-progress",
        "demo",
        "--out",
        str(out),
        "--set",
        'stages=["tokenizer"]',
        "--set",
        "tokenizer.quantizer=null",
    ]  # nothing runs: only the run directory is exercised
    assert main(demo) == 0
    capsys.readouterr()
    assert main(demo) == 2
    assert error_line(capsys) == (
        f"vqtouch: error: {out} already holds a run; continue it with --resume {out}, "
        "start it afresh with --overwrite, or choose another --out"
    )
    (out / "stale.txt").write_text("from the first run")
    assert main([*demo, "--overwrite"]) == 0
    assert not (out / "stale.txt").exists() and (out / "report.md").is_file()


def _free_port():
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def test_data_parallel_ranks_share_rank_zeros_run_directory(tmp_path):
    """Under torchrun every rank runs the command; only rank 0 owns (locks, writes) the run."""
    run = tmp_path / "run"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "torch.distributed.run",
            "--nproc_per_node",
            "2",
            "--master_port",
            str(_free_port()),
            "-m",
            "vqtouch.plugins.cli",
            *train_args(run, 64),
        ],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert json.loads((run / "eval.json").read_text())["step"] == 4
    assert codebook_in_header(run / "checkpoints" / "step-00000004") == 64


def test_a_run_that_failed_before_writing_anything_starts_again_without_overwrite(tmp_path, capsys):
    """Bad data or a full disk stop a run after config.json was written; the same command again must
    not be refused as if results were at stake."""
    run = tmp_path / "run"
    images = tmp_path / "images" / "class_a"
    images.mkdir(parents=True)
    (images / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n not an image")
    bad = ["--no-progress", "train", "tokenizer", "--out", str(run)]
    for override in [
        *(o for o in TINY if not o.startswith("data.dataset.")),
        'data.dataset={"name": "image_folder", "root": "' + str(images.parent) + '"}',
    ]:
        bad += ["--set", override]
    assert main(bad) == 2
    assert sorted(p.name for p in run.iterdir()) == [".vqtouch.lock", "checkpoints", "config.json", "env.json"]
    capsys.readouterr()
    assert main(train_args(run, 32)) == 0
    err = capsys.readouterr().err
    assert err.startswith(
        f"vqtouch: warning: {run} holds a run that stopped before writing any result; starting afresh in it\n"
    )
    # A run with results is still refused.
    assert main(train_args(run, 32)) == 2
    assert "already holds a run" in capsys.readouterr().err

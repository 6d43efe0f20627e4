"""Recovery as the command line shows it: every reader of a run skips
an unusable newest step with a one-line warning, a resume never silently starts over, an
interrupted command says only what it saved, and ``reconstruct --images`` takes the reader
options that the reader's errors name."""

import json
import pathlib
import shutil

import pytest
from PIL import Image

from vqtouch.plugins.cli.app import main

TINY = [
    "tokenizer.autoencoder.channels=16",
    "tokenizer.autoencoder.norm_groups=8",
    "tokenizer.autoencoder.channel_multipliers=[1,2]",
    "tokenizer.autoencoder.z_channels=16",
    "tokenizer.autoencoder.embed_dim=8",
    "tokenizer.quantizer.codebook_size=32",
    "data.image_size=32",
    "data.batch_size=4",
    "data.dataset.num_samples=12",
    "tokenizer.train.steps=4",
    "tokenizer.train.checkpoint_every=2",
    "tokenizer.train.log_every=1",
    "tokenizer.loss.perceptual=none",
    "tokenizer.discriminator=null",
    'metrics=[{"name": "psnr"}]',
]


def train_args(out, *extra):
    args = ["--no-progress", "train", "tokenizer", "--out", str(out)]
    for override in [*TINY, *extra]:
        args += ["--set", override]
    return args


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory):
    """A tiny tokenizer trained 4 steps, with complete checkpoints at steps 2 and 4."""
    out = tmp_path_factory.mktemp("trained") / "run"
    assert main(train_args(out)) == 0
    assert sorted(p.name for p in (out / "checkpoints").iterdir()) == ["step-00000002", "step-00000004"]
    return out


@pytest.fixture
def run_copy(trained_run, tmp_path):
    return pathlib.Path(shutil.copytree(trained_run, tmp_path / "run"))


def truncate(path, keep=100):
    path.write_bytes(path.read_bytes()[:keep])


def metric_steps(run):
    """The steps of the training lines of metrics.jsonl (checkpoints add val_loss lines of their own)."""
    lines = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    return [line["step"] for line in lines if "val_loss" not in line]


def damage_header(path):
    """Rewrite a checkpoint file with an unparsable ``vqtouch.step`` header (an edited or damaged header)."""
    from safetensors import safe_open
    from safetensors.torch import save_file

    with safe_open(str(path), framework="pt") as handle:
        header = {**handle.metadata(), "vqtouch.step": "two"}
        tensors = {key: handle.get_tensor(key) for key in handle.keys()}
    save_file(tensors, str(path), metadata=header)


@pytest.mark.parametrize("damage", ["truncated", "missing", "header"])
def test_reconstruct_falls_back_past_a_damaged_newest_step_with_a_one_line_warning(run_copy, tmp_path, capsys, damage):
    module = run_copy / "checkpoints" / "step-00000004" / "autoencoder.safetensors"
    {"truncated": truncate, "missing": lambda path: path.unlink(), "header": damage_header}[damage](module)
    capsys.readouterr()
    out = tmp_path / "recon"
    assert main(["reconstruct", "--run", str(run_copy), "--real-frames", "gelsight", "--out", str(out)]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    why = {
        "missing": "is missing",
        "truncated": "is not a readable safetensors file",
        "header": "has a damaged vqtouch header (vqtouch.step is 'two', not a step number)",
    }[damage]
    assert len(err) == 1 and err[0].startswith(
        f"vqtouch: warning: checkpoint {module.parent} skipped: autoencoder.safetensors {why}"
    ), err
    assert json.loads((out / "reconstruct.json").read_text())["checkpoint"].endswith("step-00000002")


def test_resume_falls_back_past_a_truncated_newest_step_and_continues_exactly(run_copy, trained_run, capsys):
    truncate(run_copy / "checkpoints" / "step-00000004" / "quantizer.safetensors")
    capsys.readouterr()
    assert main(["--no-progress", "train", "tokenizer", "--resume", str(run_copy)]) == 0
    captured = capsys.readouterr()
    assert f"resumed {run_copy} at step 2 (step-00000002)" in captured.out
    assert captured.err.count("vqtouch: warning: checkpoint ") == 1
    assert metric_steps(run_copy) == [1, 2, 3, 4]
    # Steps 3 and 4 trained again from step 2's state give the uninterrupted run's losses.
    assert (run_copy / "metrics.jsonl").read_text() == (trained_run / "metrics.jsonl").read_text()


def test_resume_of_a_run_without_any_usable_step_is_refused_not_restarted(run_copy, capsys):
    for step in ("step-00000002", "step-00000004"):
        (run_copy / "checkpoints" / step / "trainer_state.safetensors").unlink()
    metrics_before = (run_copy / "metrics.jsonl").read_text()
    capsys.readouterr()
    assert main(["--no-progress", "train", "tokenizer", "--resume", str(run_copy)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert err.strip() == (
        f"vqtouch: error: stage 'tokenizer' failed: {run_copy / 'checkpoints'}: holds 2 "
        "checkpoint folder(s) but no complete one (the newest, step-00000004, has no "
        "trainer_state.safetensors: its save was interrupted); restore a step folder from a copy, "
        "or train the run again with --overwrite"
    )
    assert (run_copy / "metrics.jsonl").read_text() == metrics_before  # nothing rewound, nothing trained


def test_resume_of_a_run_killed_before_its_first_checkpoint_starts_at_step_0(run_copy, capsys):
    shutil.rmtree(run_copy / "checkpoints")
    (run_copy / "checkpoints").mkdir()
    capsys.readouterr()
    assert main(["--no-progress", "train", "tokenizer", "--resume", str(run_copy)]) == 0
    assert "resumed" not in capsys.readouterr().out
    assert metric_steps(run_copy) == [1, 2, 3, 4]  # the killed attempt's lines are dropped, not duplicated


@pytest.mark.parametrize("saved", [False, True])
def test_an_interrupted_training_says_only_what_it_saved(tmp_path, capsys, monkeypatch, saved):
    """Ctrl-C before the trainer saved anything used to print "the checkpoint is saved"."""
    from vqtouch.plugins.training.trainer import TrainingInterrupted
    from vqtouch.plugins.tokenizer import command_handlers

    out = tmp_path / "run"
    folder = out / "checkpoints" / "step-00000003"

    def interrupted(*args, **kwargs):
        if saved:
            raise TrainingInterrupted("SIGINT", 3, folder)
        raise KeyboardInterrupt

    monkeypatch.setattr(command_handlers, "run_stage", interrupted)
    assert main(train_args(out)) == 130  # SIGINT's 128 + 2, and Ctrl-C's
    err = capsys.readouterr().err.strip()
    assert "checkpoint is saved" not in err
    if saved:
        assert err == (
            f"vqtouch: training stopped by SIGINT after step 3; checkpoint saved: {folder}; resume with: "
            f"vqtouch train tokenizer --resume {out}"
        )
    else:
        assert err == (
            "vqtouch: interrupted before any checkpoint was written; nothing to resume: start again with "
            f"--overwrite --out {out}"
        )


def _image_folder(root, corrupt=True):
    for index in range(3):
        folder = root / "ridges"
        folder.mkdir(parents=True, exist_ok=True)
        Image.new("RGB", (40, 40), (40 * index, 90, 160)).save(folder / f"{index}.png")
    if corrupt:
        (root / "ridges" / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n not an image")
    return root


def test_reconstruct_images_takes_the_reader_options_its_errors_name(trained_run, tmp_path, capsys):
    images = _image_folder(tmp_path / "images")
    out = tmp_path / "recon"
    capsys.readouterr()
    assert main(["reconstruct", "--run", str(trained_run), "--images", str(images), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "broken.png" in err and "set lenient=true" in err
    assert (
        main(
            [
                "reconstruct",
                "--run",
                str(trained_run),
                "--images",
                str(images),
                "--images-option",
                "lenient=true",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    result = json.loads((out / "reconstruct.json").read_text())
    assert result["images"] == 3 and result["checkpoint"].endswith("step-00000004")
    # The same options as a dataset block.
    block = json.dumps({"root": str(images), "lenient": True})
    assert main(["reconstruct", "--run", str(trained_run), "--images", block, "--out", str(tmp_path / "b")]) == 0


def test_reconstruct_reads_a_folder_that_holds_one_sensors_frames(trained_run, tmp_path, capsys):
    """Frames directly in a folder (no class sub-folders), as `cluster` and `adapt` read them: each
    constant frame is scored against itself at the tokenizer's size (a constant image resizes to the
    same constant whatever the filter), so the record's PSNR is that of an independent reconstruction."""
    import torch

    from vqtouch.core import load_plugins
    from vqtouch.plugins.tokenizer import load_tokenizer, reconstruct_all

    host = load_plugins(autoload=False)
    frames = tmp_path / "frames"
    frames.mkdir()
    colours = [(30, 90, 160), (120, 60, 200), (200, 180, 40)]
    for index, colour in enumerate(colours):
        Image.new("RGB", (40, 40), colour).save(frames / f"frame_{index}.png")
    out = tmp_path / "recon"
    assert main(["reconstruct", "--run", str(trained_run), "--images", str(frames), "--out", str(out)]) == 0
    record = json.loads((out / "reconstruct.json").read_text())
    tokenizer, _ = load_tokenizer(trained_run, host)
    size = record["image_size"]
    images = torch.tensor(colours, dtype=torch.float32).div(255).view(3, 3, 1, 1).expand(3, 3, size, size)
    metric = host.build("metric", "psnr")
    metric.update(reconstruct_all(tokenizer, images).detach(), images)
    assert record["images"] == 3 and record["psnr"] == pytest.approx(float(metric.compute()), abs=1e-3)
    capsys.readouterr()
    with_option = ["--images", str(frames), "--images-option", "lenient=true", "--out", str(tmp_path / "o")]
    assert main(["reconstruct", "--run", str(trained_run), *with_option]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "holds its images directly" in err and "drop --images-option" in err


@pytest.mark.parametrize(
    "option, message",
    [
        ("lenient", "--images-option 'lenient': give one reader option as KEY=VALUE"),
        ("image_size=64", "--images-option 'image_size=64': give one reader option as KEY=VALUE"),
        ("lenent=true", "unknown option 'lenent'"),
    ],
)
def test_reconstruct_images_option_errors_are_one_line(trained_run, tmp_path, capsys, option, message):
    images = _image_folder(tmp_path / "images", corrupt=False)
    capsys.readouterr()
    assert (
        main(
            [
                "reconstruct",
                "--run",
                str(trained_run),
                "--images",
                str(images),
                "--images-option",
                option,
                "--out",
                str(tmp_path / "out"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.startswith("vqtouch: error: ") and err.count("\n") == 1 and message in err, err


def test_step_best_reads_the_checkpoint_that_scored_best_on_the_held_out_split(trained_run, tmp_path, capsys):
    evaluation = json.loads((trained_run / "eval.json").read_text())
    losses = {
        json.loads(line)["step"]: json.loads(line)["val_loss"]
        for line in (trained_run / "metrics.jsonl").read_text().splitlines()
        if "val_loss" in line
    }
    assert sorted(losses) == [2, 4] and evaluation["best_step"] == min(losses, key=losses.get)
    out = tmp_path / "best"
    assert (
        main(
            ["reconstruct", "--run", str(trained_run), "--step", "best", "--real-frames", "gelsight", "--out", str(out)]
        )
        == 0
    )
    folder = json.loads((out / "reconstruct.json").read_text())["checkpoint"]
    assert folder == str(trained_run / "checkpoints" / f"step-{evaluation['best_step']:08d}")


def test_step_best_of_a_run_that_held_out_nothing_is_one_line(tmp_path, capsys):
    run = tmp_path / "run"
    assert main(train_args(run, "data.val_fraction=0")) == 0
    capsys.readouterr()
    assert main(["evaluate", "reconstruction", "--run", str(run), "--step", "best", "--split", "all"]) == 2
    assert capsys.readouterr().err == (
        f"vqtouch: error: {run}: no best checkpoint recorded (the run scored no "
        "held-out samples: train.keep_best=false or data.val_fraction=0); give a step "
        "number\n"
    )


def test_a_command_stopped_by_sigterm_exits_as_a_shell_reports_it(tmp_path, capsys, monkeypatch):
    """143 (128 + SIGTERM) tells a scheduler the job was terminated; Ctrl-C keeps 130."""
    from vqtouch.plugins.training.trainer import TrainingInterrupted
    from vqtouch.plugins.tokenizer import command_handlers

    def terminated(*args, **kwargs):
        raise TrainingInterrupted("SIGTERM", 1, tmp_path / "run" / "checkpoints" / "step-00000001")

    monkeypatch.setattr(command_handlers, "run_stage", terminated)
    assert main(train_args(tmp_path / "run")) == 143
    assert "training stopped by SIGTERM after step 1" in capsys.readouterr().err

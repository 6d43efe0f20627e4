"""Errors that reach the user are one line, ``vqtouch: error: ...``, with exit status 2.

Each case here once ended in a traceback (or trained and then crashed); ``--debug`` or
``VQTOUCH_DEBUG=1`` shows the traceback on purpose.
"""

import errno
import json
import os
import pathlib
import shutil

import dataset_fixtures
import pytest
import torch
from safetensors import safe_open
from safetensors.torch import save_file

from vqtouch.core import DatasetError, VqtouchError
from vqtouch.plugins.cli.app import main

TINY_TRAIN = [
    "tokenizer.autoencoder.channels=16",
    "tokenizer.autoencoder.norm_groups=8",
    "tokenizer.autoencoder.channel_multipliers=[1,2]",
    "tokenizer.autoencoder.z_channels=16",
    "tokenizer.autoencoder.embed_dim=8",
    "tokenizer.quantizer.codebook_size=32",
    "data.image_size=32",
    "data.batch_size=4",
    "tokenizer.train.steps=2",
    "tokenizer.loss.perceptual=none",
    "tokenizer.discriminator=null",
    'metrics=[{"name": "psnr"}, {"name": "ssim"}]',
]


def train_args(out, *extra):
    """``vqtouch train tokenizer`` of a tiny tokenizer on 12 procedural samples, into ``out``."""
    args = ["--no-progress", "train", "tokenizer", "--out", str(out), "--set", "data.dataset.num_samples=12"]
    for override in [*TINY_TRAIN, *extra]:
        args += ["--set", override]
    return args


def one_error_line(capsys) -> str:
    """The single stderr line of a failed command, without its prefix (asserts it is one line)."""
    err = capsys.readouterr().err
    assert err.startswith("vqtouch: error: ") and err.count("\n") == 1, err
    return err[len("vqtouch: error: ") :].rstrip("\n")


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory):
    """A trained tiny tokenizer run; tests damage copies of it."""
    out = tmp_path_factory.mktemp("trained") / "run"
    assert main(train_args(out)) == 0
    return out


@pytest.fixture
def run_copy(trained_run, tmp_path):
    return pathlib.Path(shutil.copytree(trained_run, tmp_path / "run"))


def rewrite_checkpoint(path, tensors=None, **metadata):
    """Rewrite a safetensors file with other tensors and/or header entries."""
    with safe_open(str(path), framework="pt") as handle:
        header = {**handle.metadata(), **metadata}
        tensors = tensors or {key: handle.get_tensor(key) for key in handle.keys()}
    save_file(tensors, str(path), metadata=header)


# -- OSError while creating the run ------------------------------------------------------------


@pytest.fixture
def refuse_mkdir(monkeypatch):
    """``refuse_mkdir(folder, code)``: creating ``folder`` or anything in it fails with OSError ``code``.

    The suite may run as root, which may write anywhere, so a read-only folder is simulated.
    """
    real_mkdir = pathlib.Path.mkdir

    def refuse(folder, code):
        def refusing_mkdir(self, *args, **kwargs):
            if self == folder or folder in self.parents:
                raise {errno.EACCES: PermissionError}.get(code, OSError)(code, os.strerror(code), str(self))
            return real_mkdir(self, *args, **kwargs)

        monkeypatch.setattr(pathlib.Path, "mkdir", refusing_mkdir)

    return refuse


@pytest.mark.parametrize("code", [errno.EACCES, errno.EROFS, errno.ENOSPC])
def test_unwritable_output_dir_is_one_line(tmp_path, capsys, refuse_mkdir, code):
    output_dir = tmp_path / "readonly"
    refuse_mkdir(output_dir, code)
    assert main(["demo", "--set", f"output_dir={output_dir}"]) == 2
    line = one_error_line(capsys)
    assert line.startswith(f"{output_dir}/tour-") and f": {os.strerror(code)}; " in line
    assert "--out" in line and "output_dir" in line


@pytest.mark.parametrize("below", [False, True])
def test_out_naming_an_existing_file_is_one_line(tmp_path, capsys, below):
    blocker = tmp_path / "taken"
    blocker.write_text("")
    out = blocker / "run" if below else blocker
    assert main(["demo", "--out", str(out)]) == 2
    line = one_error_line(capsys)
    assert line.startswith(str(blocker)) and "--out" in line


# -- --debug and VQTOUCH_DEBUG ------------------------------------------------------------------


def test_debug_flag_shows_the_traceback_then_the_line(tmp_path, capsys, refuse_mkdir):
    refuse_mkdir(tmp_path / "run", errno.EACCES)
    assert main(["--debug", "demo", "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("Traceback (most recent call last):") and "\nPermissionError: [Errno 13]" in err
    assert err.splitlines()[-1] == (
        f"vqtouch: error: {tmp_path / 'run'}: Permission denied; fix its permissions, or "
        "write the run elsewhere (--out or output_dir)"
    )


@pytest.mark.parametrize("value, shown", [("1", True), ("0", False), ("", False)])
def test_vqtouch_debug_environment_variable(capsys, monkeypatch, value, shown):
    monkeypatch.setenv("VQTOUCH_DEBUG", value)
    assert main(["config", "show", "no-such-scene"]) == 2
    err = capsys.readouterr().err
    assert ("Traceback (most recent call last):" in err) == shown
    assert err.splitlines()[-1].startswith("vqtouch: error: unknown scene 'no-such-scene'")


# -- reading runs and config files --------------------------------------------------------------


def test_evaluate_a_missing_run_directory_is_one_line(tmp_path, capsys):
    missing = tmp_path / "nowhere"
    assert main(["evaluate", "reconstruction", "--run", str(missing)]) == 2
    assert one_error_line(capsys) == f"{missing}: not a run directory (no config.json)"


@pytest.mark.parametrize("command", [["evaluate", "reconstruction", "--run"], ["train", "tokenizer", "--resume"]])
def test_corrupt_run_config_json_is_one_line(run_copy, capsys, command):
    (run_copy / "config.json").write_text("{not json", encoding="utf-8")
    assert main([*command, str(run_copy)]) == 2
    assert "not valid JSON" in one_error_line(capsys)


def test_corrupt_run_config_json_names_the_file(run_copy, capsys):
    (run_copy / "config.json").write_text("{not json", encoding="utf-8")
    assert main(["evaluate", "reconstruction", "--run", str(run_copy)]) == 2
    assert one_error_line(capsys).startswith(f"{run_copy / 'config.json'}: not valid JSON")


def test_non_utf8_config_file_is_one_line(tmp_path, capsys):
    path = tmp_path / "latin1.toml"
    path.write_bytes('description = "Kraftsensor für Gelsight"\n'.encode("latin-1"))
    assert main(["config", "show", "reconstruction", "--config", str(path)]) == 2
    line = one_error_line(capsys)
    assert line.startswith(f"{path}: not UTF-8 text") and "save it as UTF-8" in line


# -- checkpoints and trained weights ----------------------------------------------------------


def test_unparsable_step_header_is_one_line(run_copy, capsys):
    path = run_copy / "checkpoints" / "step-00000002" / "autoencoder.safetensors"
    rewrite_checkpoint(path, **{"vqtouch.step": "two"})
    assert main(["evaluate", "reconstruction", "--run", str(run_copy)]) == 2
    assert one_error_line(capsys) == (
        f"{run_copy / 'checkpoints'}: holds 1 checkpoint folder(s) but no complete one (the newest, step-00000002, "
        "is unusable: autoencoder.safetensors has a damaged vqtouch header (vqtouch.step is 'two', not a step "
        "number)); restore a step folder from a copy, or train the run again with --overwrite"
    )
    # load() itself refuses it too, naming the file (a checkpoint file used outside a run).
    from vqtouch.core import CheckpointError, load, load_plugins

    with pytest.raises(CheckpointError, match=r"damaged vqtouch header \(vqtouch.step is 'two', not a step number\)"):
        load(path, host=load_plugins(autoload=False))


def test_nan_weights_are_refused_before_the_metrics(run_copy, capsys):
    path = run_copy / "checkpoints" / "step-00000002" / "autoencoder.safetensors"
    with safe_open(str(path), framework="pt") as handle:
        tensors = {key: handle.get_tensor(key) for key in handle.keys()}
    rewrite_checkpoint(
        path,
        {
            key: torch.full_like(value, float("nan")) if value.is_floating_point() else value
            for key, value in tensors.items()
        },
    )
    assert main(["evaluate", "reconstruction", "--run", str(run_copy)]) == 2
    line = one_error_line(capsys)
    # load() refuses them, naming the file, before anything is reconstructed or scored.
    assert line.startswith(f"{path}: ") and "weight tensor(s) hold NaN or Inf (first " in line
    assert "--step" in line and "learning_rate" in line
    # So does `reconstruct`, which once ended in a traceback.
    assert (
        main(["reconstruct", "--run", str(run_copy), "--real-frames", "gelsight", "--out", str(run_copy.parent / "r")])
        == 2
    )
    assert one_error_line(capsys).startswith(f"{path}: ")


# -- data ------------------------------------------------------------------------------------


class _Failing(torch.utils.data.Dataset):
    def __len__(self):
        return 4

    def __getitem__(self, index):
        raise DatasetError(f"cannot decode image /data/{index}.png: OSError: image file is truncated")


def test_one_line_recovers_the_message_of_a_dataloader_worker_error():
    from vqtouch.core.errors import one_line

    loader = torch.utils.data.DataLoader(_Failing(), batch_size=2, num_workers=1)
    with pytest.raises(DatasetError) as info:
        next(iter(loader))
    assert "\n" in str(info.value)  # PyTorch re-raises it with the worker's traceback in the message
    assert one_line(str(info.value)) == "cannot decode image /data/0.png: OSError: image file is truncated"
    assert one_line(f"stage 'tokenizer' failed: {info.value}") == (
        "stage 'tokenizer' failed: cannot decode image /data/0.png: OSError: image file is truncated"
    )
    assert one_line("first\n  second\n") == "first; second"


def test_dataset_error_in_a_dataloader_worker_is_its_own_one_line(tmp_path, capsys):
    images = tmp_path / "images"
    for number in range(8):
        dataset_fixtures.truncate_pixels(
            dataset_fixtures.write_sample(images / "a" / f"{number}.png", number, "tactile")
        )
    args = [
        "--no-progress",
        "train",
        "tokenizer",
        "--out",
        str(tmp_path / "run"),
        "--set",
        "data.dataset.name=image_folder",
        "--set",
        f"data.dataset.root={images}",
        "--set",
        "data.num_workers=1",
    ]
    for override in TINY_TRAIN:
        args += ["--set", override]
    assert main(args) == 2
    line = one_error_line(capsys)
    assert line.startswith(f"stage 'tokenizer' failed: cannot decode image {images / 'a'}")
    assert line.endswith(": OSError: image file is truncated")


def test_evaluate_reconstruction_refuses_an_empty_dataset(host):
    from vqtouch.core import BuildContext
    from vqtouch.core.errors import NothingToEvaluateError
    from vqtouch.plugins.tokenizer.training import Tokenizer, evaluate_reconstruction

    context = BuildContext(image_size=32)
    autoencoder = host.build(
        "autoencoder",
        {
            "name": "vqgan",
            "channels": 16,
            "norm_groups": 8,
            "channel_multipliers": [1, 2],
            "z_channels": 16,
            "embed_dim": 8,
        },
        context,
    )
    quantizer = host.build(
        "quantizer",
        {"name": "vq", "codebook_size": 8},
        context.model_copy(update={"latent_dim": autoencoder.latent_channels}),
    )
    metrics = {"psnr": host.build("metric", "psnr")}
    with pytest.raises(NothingToEvaluateError) as info:
        evaluate_reconstruction(Tokenizer(autoencoder, quantizer), [], metrics)
    assert isinstance(info.value, VqtouchError) and "\n" not in str(info.value)
    assert str(info.value).startswith("nothing to evaluate: the dataset has no samples")


def test_evaluate_a_run_without_held_out_samples_is_one_line(tmp_path, capsys):
    out = tmp_path / "run"
    main(train_args(out, "data.val_fraction=0"))  # trains; the evaluation has nothing to score
    capsys.readouterr()
    assert main(["evaluate", "reconstruction", "--run", str(out)]) == 2
    line = one_error_line(capsys)
    assert line.startswith("nothing to evaluate: the dataset has no samples") and "--split all" in line
    assert main(["evaluate", "reconstruction", "--run", str(out), "--split", "all"]) == 0


def test_val_fraction_0_trains_and_states_why_evaluation_was_skipped(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(train_args(out, "data.val_fraction=0")) == 0
    result = json.loads((out / "eval.json").read_text())
    assert result["evaluation"] == "skipped: no held-out samples (data.val_fraction=0)"
    assert result["step"] == 2 and result["val_samples"] == 0 and result["train_samples"] == 12
    assert not (out / "reconstructions.png").exists()


def test_batch_larger_than_the_training_split_fails_before_training(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(train_args(out, "data.batch_size=20")) == 2
    assert one_error_line(capsys) == (
        "stage 'tokenizer' failed: the dataset has 11 samples, fewer than one global "
        "batch (20 x 1 processes); lower data.batch_size"
    )
    assert not list((out / "checkpoints").iterdir())

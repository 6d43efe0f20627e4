import json

import pytest

from vqtouch.core import resolve_config
from vqtouch.plugins.utils.seeding import seed_everything
from vqtouch.plugins.runtime.records import config_hash, recorded_config
from vqtouch.plugins.runtime.run_dir import RunDir


def test_run_dir_name_and_files(host, tmp_path):
    config = resolve_config("label-to-touch", overrides=[f"output_dir={tmp_path}", "seed=3"], host=host)
    run = RunDir.create(config, argv=["vqtouch", "demo"], host=host)
    assert run.path.parent == tmp_path
    assert run.path.name.startswith("label-to-touch-") and run.path.name.endswith(config_hash(config))
    recorded = json.loads((run.path / "config.json").read_text())
    assert recorded == recorded_config(config, host)
    # Only the sections of the stages it runs (and those holding their slots); it reads back as the config.
    assert "generator" in recorded and "cluster" not in recorded and "cluster" in config.to_dict()
    assert RunDir.open(run.path).load_config(host) == config
    env = json.loads((run.path / "env.json").read_text())
    assert env["argv"] == ["vqtouch", "demo"] and env["seed"] == 3
    assert {"torch", "torchvision", "pydantic", "pluggy", "safetensors"} <= set(env["versions"])
    run.log_metrics("tokenizer", 10, {"loss": 0.5})
    run.log_metrics("tokenizer", 20, {"loss": 0.25})
    lines = [json.loads(line) for line in (run.path / "metrics.jsonl").read_text().splitlines()]
    assert lines == [{"stage": "tokenizer", "step": 10, "loss": 0.5}, {"stage": "tokenizer", "step": 20, "loss": 0.25}]


def test_config_hash_is_stable_and_sensitive(host):
    a = resolve_config("label-to-touch", host=host)
    b = resolve_config("label-to-touch", host=host)
    c = resolve_config("label-to-touch", overrides=["seed=1"], host=host)
    assert config_hash(a) == config_hash(b) != config_hash(c)


def test_seed_everything_is_reproducible():
    import torch

    seed_everything(123)
    first = torch.rand(3)
    seed_everything(123)
    assert torch.equal(first, torch.rand(3))


def test_env_records_where_every_component_came_from(host, tmp_path):
    from vqtouch.core import __version__

    config = resolve_config("label-to-touch", overrides=[f"output_dir={tmp_path}"], host=host)
    env = json.loads((RunDir.create(config, host=host).path / "env.json").read_text())
    components = env["components"]
    assert components["generator.conditioners.0"] == {
        "kind": "conditioner",
        "name": "label",
        "plugin": "label",
        "package": "vqtouch",
        "version": __version__,
    }
    assert components["metrics.1"]["name"] == "ssim" and components["tokenizer.autoencoder"]["kind"] == "autoencoder"
    filled = {path for path, info in host.slots.items() if config.slot(path) not in (None, [])}
    assert {key.rsplit(".", 1)[0] if key.rsplit(".", 1)[-1].isdigit() else key for key in components} == filled
    assert env["plugins"]["label"]["package"] == "vqtouch"


def test_open_run_and_reload_its_config(host, tmp_path):
    from vqtouch.core import ConfigError

    config = resolve_config("label-to-touch", overrides=[f"output_dir={tmp_path}", "seed=5"], host=host)
    run = RunDir.create(config, host=host)
    reopened = RunDir.open(run.path)
    assert reopened.checkpoints == run.path / "checkpoints"
    assert reopened.load_config(host) == config
    with pytest.raises(ConfigError, match="not a run directory"):
        RunDir.open(tmp_path / "nothing-here")


def test_reloading_a_run_whose_plugin_is_gone_names_its_distribution(host, tmp_path):
    from vqtouch.core import ConfigError, __version__, load_plugins

    config = resolve_config("label-to-touch", overrides=[f"output_dir={tmp_path}"], host=host)
    run = RunDir.create(config, host=host)
    without = load_plugins(autoload=False, block=["label"])
    with pytest.raises(ConfigError) as info:
        run.load_config(without)
    assert str(info.value) == (
        f"{run.path}: generator.conditioners.0 uses conditioner 'label' from vqtouch "
        f"{__version__} (plugin 'label'), which is not installed here; pip install vqtouch"
    )


def test_third_party_run_component_is_named_from_env(third_party_conditioner, tmp_path):
    from vqtouch.core import ConfigError, load_plugins

    with_plugin = load_plugins(autoload=False, extra=[third_party_conditioner])
    config = resolve_config(
        "label-to-touch",
        overrides=[f"output_dir={tmp_path}", 'generator.conditioners=[{"name": "x"}]'],
        host=with_plugin,
    )
    run = RunDir.create(config, host=with_plugin)
    assert run.load_config(with_plugin) == config
    plain = load_plugins(autoload=False)
    # An in-memory module has no distribution: the plugin name is all there is to name.
    with pytest.raises(
        ConfigError,
        match=r"uses conditioner 'x' from pkg_plugin \(plugin 'pkg_plugin'\), which is "
        r"not installed here; pip install pkg_plugin",
    ):
        run.load_config(plain)
    # What an installed distribution records in env.json.
    env = json.loads((run.path / "env.json").read_text())
    env["components"]["generator.conditioners.0"].update(package="pkg", version="1.0")
    run.write_json("env.json", env)
    with pytest.raises(ConfigError) as info:
        run.load_config(plain)
    assert str(info.value).endswith(
        "generator.conditioners.0 uses conditioner 'x' from pkg 1.0 (plugin 'pkg_plugin'), "
        "which is not installed here; pip install pkg"
    )


# -- one run per directory -----------------------------------------------------------


def _tiny_config(host, tmp_path, *overrides, autoencoder="dm_vqgan"):
    return resolve_config(
        "reconstruction",
        overrides=[
            f"output_dir={tmp_path}",
            f"tokenizer.autoencoder.name={autoencoder}",
            "tokenizer.autoencoder.channels=16",
            "tokenizer.autoencoder.norm_groups=8",
            "tokenizer.autoencoder.channel_multipliers=[1,2]",
            "tokenizer.autoencoder.z_channels=16",
            "tokenizer.autoencoder.embed_dim=8",
            "tokenizer.quantizer.codebook_size=32",
            "data.image_size=32",
            *overrides,
        ],
        host=host,
    )


def test_create_into_a_directory_holding_a_run_is_refused_unless_overwrite(host, tmp_path):
    from vqtouch.core import ConfigError

    path = tmp_path / "run"
    first = RunDir.create(_tiny_config(host, tmp_path), host=host, path=path)
    first.log_metrics("tokenizer", 1, {"loss": 1.0})
    (first.checkpoints / "step-00000004").mkdir()
    first.close()
    second = _tiny_config(host, tmp_path, "tokenizer.quantizer.codebook_size=64")
    with pytest.raises(ConfigError) as info:
        RunDir.create(second, host=host, path=path)
    assert str(info.value) == (
        f"{path} already holds a run; continue it with --resume {path}, start it afresh "
        "with --overwrite, or choose another --out"
    )
    assert json.loads((path / "config.json").read_text())["tokenizer"]["quantizer"]["codebook_size"] == 32
    with RunDir.create(second, host=host, path=path, overwrite=True) as run:
        assert json.loads((path / "config.json").read_text())["tokenizer"]["quantizer"]["codebook_size"] == 64
        assert not (path / "metrics.jsonl").exists() and list(run.checkpoints.iterdir()) == []


def test_create_accepts_an_empty_directory_and_refuses_to_wipe_a_non_run_folder(host, tmp_path):
    from vqtouch.core import ConfigError

    empty = tmp_path / "empty"
    empty.mkdir()
    RunDir.create(_tiny_config(host, tmp_path), host=host, path=empty).close()
    assert (empty / "config.json").is_file()
    folder = tmp_path / "photos"
    folder.mkdir()
    (folder / "holiday.png").write_bytes(b"not a run")
    for overwrite in (False, True):
        with pytest.raises(ConfigError) as info:
            RunDir.create(_tiny_config(host, tmp_path), host=host, path=folder, overwrite=overwrite)
        assert str(info.value) == (
            f"{folder} is not empty and is not a run directory (no config.json); choose an "
            "empty or new --out (--overwrite only empties run directories)"
        )
    assert sorted(p.name for p in folder.iterdir()) == ["holiday.png"]  # untouched, not even a lock file


def test_a_run_being_created_is_not_taken_for_a_foreign_folder(host, tmp_path):
    """Between taking the lock and renaming config.json into place, a run holds only its lock file
    and config.json's temporary file; a second writer must see a run there, not someone's folder."""
    from vqtouch.core import ConfigError
    from vqtouch.plugins.runtime.run_dir import LOCK_NAME

    path = tmp_path / "run"
    path.mkdir()
    (path / LOCK_NAME).write_text("12345\n")
    (path / ".config.json.k2j4.tmp").write_text("{")
    with pytest.raises(ConfigError, match="holds a run without its config.json"):
        RunDir.create(_tiny_config(host, tmp_path), host=host, path=path)
    RunDir.create(_tiny_config(host, tmp_path), host=host, path=path, overwrite=True).close()
    assert sorted(p.name for p in path.iterdir()) == [LOCK_NAME, "checkpoints", "config.json", "env.json"]


def test_a_run_has_one_writer_at_a_time_in_one_process(host, tmp_path):
    import os

    from vqtouch.core import ConfigError

    run = RunDir.create(_tiny_config(host, tmp_path), host=host, path=tmp_path / "run")
    with pytest.raises(ConfigError, match=rf"is in use by another vqtouch process \(pid {os.getpid()}\)"):
        RunDir.open(run.path, for_writing=True)
    assert RunDir.open(run.path).load_config(host).seed == 0  # readers take no lock
    run.close()
    run.close()  # closing twice is harmless
    with RunDir.open(run.path, for_writing=True):
        pass


def _save_step(run, host, config, step, complete=True):
    """A checkpoint folder as the trainer writes it: one file per module (+ trainer state)."""
    import torch
    from safetensors.torch import save_file

    from vqtouch.core import Assembly, save
    from vqtouch.plugins.training.checkpoints import TRAINER_STATE

    folder = run.checkpoints / f"step-{step:08d}"
    assembly = Assembly(config, host)
    for name in ("autoencoder", "quantizer"):
        save(assembly.component(f"tokenizer.{name}"), folder / f"{name}.safetensors", step=step, host=host)
    if complete:
        # The header readers check: the trainer's JSON, naming the module files of the step.
        meta = {"step": step, "modules": ["autoencoder", "quantizer"]}
        save_file(
            {"rng.torch_cpu": torch.get_rng_state()},
            str(folder / TRAINER_STATE),
            metadata={"format": "pt", "vqtouch.trainer": json.dumps(meta)},
        )
    return folder


def test_checkpoint_is_the_newest_complete_step_of_this_run(host, tmp_path):
    from vqtouch.core import CheckpointError
    from vqtouch.plugins.runtime.run_dir import MissingCheckpointError

    config = _tiny_config(host, tmp_path)
    run = RunDir.create(config, host=host, path=tmp_path / "run")
    with pytest.raises(MissingCheckpointError) as info:
        run.checkpoint(host)
    assert str(info.value) == f"{run.path}: no checkpoint in checkpoints/; train this run first"
    two = _save_step(run, host, config, 2)
    _save_step(run, host, config, 4, complete=False)  # an interrupted save is not a checkpoint
    from vqtouch.plugins.training.checkpoints import SkippedCheckpointWarning

    with pytest.warns(SkippedCheckpointWarning, match="step-00000004 skipped: no trainer_state.safetensors"):
        assert run.checkpoint(host) == two
    assert run.checkpoint(host, step=2) == two
    with pytest.raises(MissingCheckpointError) as info:
        run.checkpoint(host, step=4)
    assert str(info.value) == (
        f"{run.checkpoints / 'step-00000004'}: unusable checkpoint (no "
        "trainer_state.safetensors: its save was interrupted); choose another step"
    )
    with pytest.raises(MissingCheckpointError, match=r"step-00000003: no such checkpoint; this run has steps 2"):
        run.checkpoint(host, step=3)
    # An older run's folder left behind, newer than this run's own steps.
    _save_step(run, host, _tiny_config(host, tmp_path, "tokenizer.quantizer.codebook_size=64"), 6)
    with pytest.raises(CheckpointError) as info:
        run.checkpoint(host)
    assert str(info.value) == (
        f"{run.checkpoints / 'step-00000006' / 'quantizer.safetensors'} was made with quantizer 'vq' "
        '{"codebook_size": 64} but the run\'s config.json says tokenizer.quantizer {"codebook_size": 32}; this folder '
        "mixes two runs: pick one of this run's own steps with --step, or retrain into an empty --out"
    )
    assert run.checkpoint(host, step=2) == two  # a step of this run is still readable


def _rewrite_header_config(path, edit):
    """Rewrite a module file's recorded component config (``vqtouch.config``) with ``edit(config)``,
    as a file saved by an older vqtouch, before an option existed, would read."""
    from safetensors import safe_open
    from safetensors.torch import save_file

    with safe_open(str(path), "pt") as handle:
        metadata = dict(handle.metadata())
        tensors = {key: handle.get_tensor(key) for key in handle.keys()}
    recorded = json.loads(metadata["vqtouch.config"])
    edit(recorded)
    save_file(tensors, str(path), metadata={**metadata, "vqtouch.config": json.dumps(recorded)})


def test_a_checkpoint_saved_before_an_option_existed_belongs_to_its_run(host, tmp_path):
    """An option added to a plugin after a checkpoint was saved is absent from its header; the run's
    config holds the option's default, which computes what the file did, so the file is the run's own."""
    from vqtouch.core import CheckpointError, read_metadata

    config = _tiny_config(host, tmp_path)
    run = RunDir.create(config, host=host, path=tmp_path / "run")
    folder = _save_step(run, host, config, 2)
    quantizer_file = folder / "quantizer.safetensors"
    recorded = json.loads(read_metadata(quantizer_file)["vqtouch.config"])
    option = next(key for key in sorted(recorded) if key not in ("name", "codebook_size"))
    _rewrite_header_config(quantizer_file, lambda header: header.pop(option))
    assert run.checkpoint(host) == folder
    # Still a mismatch when the file's value of another option is not the run's.
    _rewrite_header_config(quantizer_file, lambda header: header.update(codebook_size=64))
    with pytest.raises(CheckpointError, match=r'quantizer \'vq\' \{"codebook_size": 64\} but the run') as info:
        run.checkpoint(host)
    assert option not in str(info.value)  # the option the file predates is not named as a difference


def test_checkpoint_names_another_plugin_in_a_mixed_folder(host, tmp_path):
    from vqtouch.core import CheckpointError

    config = _tiny_config(host, tmp_path)
    run = RunDir.create(config, host=host, path=tmp_path / "run")
    _save_step(run, host, _tiny_config(host, tmp_path, autoencoder="vqgan"), 2)
    with pytest.raises(CheckpointError) as info:
        run.checkpoint(host)
    assert str(info.value).startswith(
        f"{run.checkpoints / 'step-00000002' / 'autoencoder.safetensors'} was made with "
        "autoencoder 'vqgan' but the run's config.json says tokenizer.autoencoder "
        "is 'dm_vqgan'; this folder mixes two runs"
    )

import json

import pytest

from vqtouch.core import RunDir, resolve_config, seed_everything
from vqtouch.core.runs import config_hash


def test_run_dir_name_and_files(host, tmp_path):
    config = resolve_config("label-to-touch", overrides=[f"output_dir={tmp_path}", "seed=3"], host=host)
    run = RunDir.create(config, argv=["vqtouch", "demo"], host=host)
    assert run.path.parent == tmp_path
    assert run.path.name.startswith("label-to-touch-") and run.path.name.endswith(config_hash(config))
    assert json.loads((run.path / "config.json").read_text()) == config.to_dict()
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
    assert components["generator.conditioners.0"] == {"kind": "conditioner", "name": "label", "plugin": "label",
                                                      "package": "vqtouch", "version": __version__}
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
    assert str(info.value) == (f"{run.path}: generator.conditioners.0 uses conditioner 'label' from vqtouch "
                               f"{__version__} (plugin 'label'), which is not installed here; pip install vqtouch")


def test_third_party_run_component_is_named_from_env(third_party_conditioner, tmp_path):
    from vqtouch.core import ConfigError, load_plugins

    with_plugin = load_plugins(autoload=False, extra=[third_party_conditioner])
    config = resolve_config("label-to-touch", overrides=[f"output_dir={tmp_path}",
                                                         'generator.conditioners=[{"name": "x"}]'], host=with_plugin)
    run = RunDir.create(config, host=with_plugin)
    assert run.load_config(with_plugin) == config
    plain = load_plugins(autoload=False)
    # An in-memory module has no distribution: the plugin name is all there is to name.
    with pytest.raises(ConfigError, match=r"uses conditioner 'x' from pkg_plugin \(plugin 'pkg_plugin'\), which is "
                                          r"not installed here; pip install pkg_plugin"):
        run.load_config(plain)
    # What an installed distribution records in env.json.
    env = json.loads((run.path / "env.json").read_text())
    env["components"]["generator.conditioners.0"].update(package="pkg", version="1.0")
    run.write_json("env.json", env)
    with pytest.raises(ConfigError) as info:
        run.load_config(plain)
    assert str(info.value).endswith("generator.conditioners.0 uses conditioner 'x' from pkg 1.0 (plugin 'pkg_plugin'), "
                                    "which is not installed here; pip install pkg")

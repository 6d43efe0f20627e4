import json

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

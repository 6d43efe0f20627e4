import json

import pytest

from vqtouch.core import ConfigError, ExperimentConfig, hookimpl, load_plugins, resolve_config
from vqtouch.core.config import apply_override, merge_configs, parse_override


@pytest.mark.parametrize("scene", ["reconstruction", "few-shot", "zero-shot", "cross-sensor", "vision-to-touch",
                                   "label-to-touch", "touch-to-touch"])
def test_every_scene_resolves(host, scene):
    config = resolve_config(scene, host=host)
    assert config.scene == scene and config.stages
    assert config.required_slots()  # every scene needs something
    again = ExperimentConfig.model_validate(config.to_dict(), context={"host": host})
    assert again == config  # dump -> validate round trip keeps plugin options


def test_slot_options_are_validated_at_load_with_exact_path(host):
    with pytest.raises(ConfigError) as info:
        resolve_config("label-to-touch", overrides=["conditioner.num_tokens=0"], host=host)
    assert str(info.value) == ("invalid configuration: conditioner.num_tokens: "
                               "Input should be greater than or equal to 1 (got 0)")


def test_unknown_plugin_lists_choices_and_closest(host):
    with pytest.raises(ConfigError, match=r"conditioner: unknown conditioner 'lable'; available: clip, label, "
                                          r"tactile; did you mean 'label'\?"):
        resolve_config("label-to-touch", overrides=["conditioner.name=lable"], host=host)


def test_unknown_option_lists_allowed(host):
    with pytest.raises(ConfigError, match=r"train: unknown option 'step'; allowed: .*steps.*did you mean 'steps'"):
        resolve_config("label-to-touch", overrides=["train.step=3"], host=host)


def test_literal_error_lists_allowed_values(host):
    with pytest.raises(ConfigError, match=r"device: Input should be 'auto', 'cpu' or 'cuda' \(got 'tpu'\)"):
        resolve_config("label-to-touch", overrides=["device=tpu"], host=host)


def test_changing_slot_name_resets_its_options(host):
    config = resolve_config("label-to-touch", overrides=["conditioner.name=tactile", "conditioner.width=16"],
                            host=host)
    assert config.conditioner.model_dump() == {"name": "tactile", "width": 16, "depth": 3, "token_grid": 4}


def test_slot_given_as_string(host):
    config = resolve_config("label-to-touch", overrides=["conditioner=tactile"], host=host)
    assert config.conditioner.name == "tactile"


def test_override_values_are_json_or_string():
    assert parse_override("train.steps=5") == (["train", "steps"], 5)
    assert parse_override("name=my-run") == (["name"], "my-run")
    assert parse_override("metrics=[{\"name\": \"psnr\"}]") == (["metrics"], [{"name": "psnr"}])
    for bad in ("train.steps", "=3", "a..b=1"):
        with pytest.raises(ConfigError, match="bad override"):
            parse_override(bad)


def test_list_index_overrides(host):
    config = resolve_config("label-to-touch", overrides=["metrics.1.window_size=7"], host=host)
    assert config.metrics[1].window_size == 7
    with pytest.raises(ConfigError, match="index '5' is not within a list of 2"):
        resolve_config("label-to-touch", overrides=["metrics.5.name=psnr"], host=host)


def test_cannot_descend_into_a_scalar():
    with pytest.raises(ConfigError, match="train.steps is int 3, not a section"):
        apply_override({"train": {"steps": 3}}, ["train", "steps", "x"], 1)


def test_top_level_name_is_not_a_slot_reset():
    assert apply_override({"name": "a", "seed": 1}, ["name"], "b") == {"name": "b", "seed": 1}


def test_merge_replaces_block_when_plugin_changes():
    base = {"conditioner": {"name": "label", "num_tokens": 2}, "train": {"steps": 1, "learning_rate": 0.1}}
    merged = merge_configs(base, {"conditioner": {"name": "tactile"}, "train": {"steps": 2}})
    assert merged == {"conditioner": {"name": "tactile"}, "train": {"steps": 2, "learning_rate": 0.1}}
    assert base["train"]["steps"] == 1  # inputs untouched


def test_toml_and_json_files_merge_in_order(host, tmp_path):
    toml_file = tmp_path / "a.toml"
    toml_file.write_text('seed = 7\n[train]\nsteps = 11\n[conditioner]\nname = "tactile"\nwidth = 32\n')
    json_file = tmp_path / "b.json"
    json_file.write_text(json.dumps({"train": {"learning_rate": 0.01}}))
    config = resolve_config("label-to-touch", [toml_file, json_file], ["train.steps=12"], host=host)
    assert (config.seed, config.train.steps, config.train.learning_rate) == (7, 12, 0.01)
    assert config.conditioner.name == "tactile" and config.conditioner.width == 32


@pytest.mark.parametrize("name, text, message", [
    ("missing.toml", None, "does not exist"),
    ("bad.toml", "seed = = 1", "cannot parse"),
    ("bad.json", "{", "cannot parse"),
    ("list.json", "[1, 2]", "top level must be a table"),
    ("conf.ini", "x", "unsupported config format '.ini'"),
])
def test_config_file_errors_name_the_file(host, tmp_path, name, text, message):
    path = tmp_path / name
    if text is not None:
        path.write_text(text)
    with pytest.raises(ConfigError, match=message) as info:
        resolve_config(None, [path], host=host)
    assert name in str(info.value)


def test_multiple_problems_are_reported_together(host):
    with pytest.raises(ConfigError, match=r"\(2 problems\): seed: .*; train.steps: "):
        resolve_config(None, overrides=["seed=-1", "train.steps=-1"], host=host)


def test_required_and_missing_slots(host):
    config = resolve_config("label-to-touch", host=host)
    assert config.required_slots() == ["data.dataset", "tokenizer.encoder", "tokenizer.quantizer",
                                       "tokenizer.discriminator", "conditioner", "generator", "metrics"]
    assert ("generator", "generator") in config.missing_slots()
    assert all(path != "conditioner" for _, path in config.missing_slots())
    # The discriminator is optional: an empty one is never "missing".
    no_disc = resolve_config("label-to-touch", overrides=["tokenizer.discriminator=null"], host=host)
    assert all(path != "tokenizer.discriminator" for _, path in no_disc.missing_slots())


def test_validate_experiment_hook_can_veto(make_plugin):
    @hookimpl
    def vqtouch_validate_experiment(config):
        if config.seed == 13:
            raise ConfigError("seed 13 is unlucky")

    host = load_plugins(autoload=False, extra=[make_plugin("veto", vqtouch_validate_experiment)])
    assert resolve_config(None, overrides=["seed=12"], host=host).seed == 12
    with pytest.raises(ConfigError, match="unlucky"):
        resolve_config(None, overrides=["seed=13"], host=host)


def test_config_is_frozen(host):
    config = resolve_config("label-to-touch", host=host)
    with pytest.raises(Exception):
        config.seed = 3


def test_switching_a_slots_plugin_after_setting_its_options_is_refused(host):
    # The reset would silently drop channels=32 and train the default width instead.
    with pytest.raises(ConfigError, match=r"--set tokenizer.encoder.name=vqgan selects another plugin for "
                                          r"tokenizer.encoder.*--set tokenizer.encoder.channels=32; put"):
        resolve_config("reconstruction", overrides=["tokenizer.encoder.channels=32",
                                                    "tokenizer.encoder.name=vqgan"], host=host)
    with pytest.raises(ConfigError, match="drop the earlier --set conditioner.width=16"):
        resolve_config("touch-to-touch", overrides=["conditioner.width=16", "conditioner=label"], host=host)
    with pytest.raises(ConfigError, match="drop the earlier --set tokenizer.quantizer.codebook_size=8"):
        resolve_config("reconstruction", overrides=["tokenizer.quantizer.codebook_size=8",
                                                    'tokenizer.quantizer={"name": "ema_vq"}'], host=host)
    # Name first, options after: both kept.  Re-stating the same plugin resets nothing, so it is allowed.
    config = resolve_config("reconstruction", overrides=["tokenizer.encoder.name=vqgan", "tokenizer.encoder.channels=32",
                                                         "tokenizer.encoder.name=vqgan"], host=host)
    assert config.tokenizer.encoder.name == "vqgan" and config.tokenizer.encoder.channels == 32

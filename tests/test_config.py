import json

import pytest
from pydantic import Field, ValidationError

from vqtouch.core import (
    ConfigError,
    VqtouchDeprecationWarning,
    ExperimentConfig,
    Section,
    UnknownPluginError,
    hookimpl,
    load_plugins,
    resolve_config,
    validate_experiment,
)
from vqtouch.core.config import apply_override, merge_configs, parse_override
from vqtouch.core.stages import missing_slots, required_slots

SCENES = [
    "reconstruction",
    "few-shot",
    "zero-shot",
    "cross-sensor",
    "vision-to-touch",
    "label-to-touch",
    "text-to-touch",
    "mixed-to-touch",
    "touch-to-touch",
]
BUILTIN_STAGES = ["adapt", "cluster", "fewshot", "generator", "pretrained", "reconstruct", "render", "tokenizer"]


@pytest.mark.parametrize("scene", SCENES)
def test_every_scene_resolves(host, scene):
    config = resolve_config(scene, host=host)
    assert config.scene == scene and config.stages
    assert required_slots(config, host)  # every scene needs something
    again = host.experiment_model.model_validate(config.to_dict(), context={"host": host})
    assert again == config  # dump -> validate round trip keeps plugin options
    assert validate_experiment(config.to_dict(), host) == config


@pytest.mark.parametrize("scene", SCENES)
def test_every_scene_lists_only_registered_stages(host, scene):
    config = resolve_config(scene, host=host)
    assert set(config.stages) <= set(host.stages)
    assert "evaluate" not in config.stages  # the evaluate stage is gone; scoring is part of each stage
    for stage in config.stages:
        entry = host.stage(stage)
        # Each slot a stage declares is a slot of the experiment model; a stage with a section is a field.
        assert all(path in host.slots for path in entry.slots)
        if entry.section is not None:
            assert isinstance(getattr(config, stage), entry.section)


def test_builtin_stages_and_their_sections(host):
    assert set(BUILTIN_STAGES) <= set(host.stages)
    sections = {name: entry.section.__name__ if entry.section else None for name, entry in host.stages.items()}
    assert sections == {
        "render": "RenderSection",
        "tokenizer": "TokenizerSection",
        "reconstruct": None,
        "cluster": "ClusterSection",
        "adapt": "AdaptSection",
        "generator": "GeneratorSection",
        "fewshot": "FewshotSection",
        "pretrained": "PretrainedSection",
    }
    fields = set(host.experiment_model.model_fields)
    assert {"render", "tokenizer", "cluster", "adapt", "generator"} <= fields
    assert not {"reconstruct", "train", "conditioner", "clusterer", "evaluate"} & fields
    # The base model holds only core's fields: stage sections come from the registrations.
    assert not {"render", "tokenizer", "cluster", "generator"} & set(ExperimentConfig.model_fields)
    assert set(host.slots) == {
        "sensor",
        "target_sensor",
        "paired_sensor",
        "data.dataset",
        "metrics",
        "tokenizer.autoencoder",
        "tokenizer.quantizer",
        "tokenizer.discriminator",
        "cluster.clusterer",
        "generator.model",
        "generator.conditioners",
        "generator.sampler",
        "generator.sensor_tag",
    }
    assert (host.slots["generator.conditioners"].kind, host.slots["generator.conditioners"].many) == (
        "conditioner",
        True,
    )
    assert (host.slots["tokenizer.autoencoder"].kind, host.slots["tokenizer.autoencoder"].many) == (
        "autoencoder",
        False,
    )


def test_unknown_stage_lists_the_registered_stages(host):
    available = ", ".join(sorted(host.stages))
    with pytest.raises(ConfigError) as info:
        resolve_config(None, overrides=['stages=["tokenizer", "evaluatee"]'], host=host)
    assert str(info.value).startswith(
        f"invalid configuration: stages: unknown stage 'evaluatee'; available: {available}"
    )
    with pytest.raises(UnknownPluginError, match=f"unknown stage 'evaluate'; available: {available}"):
        host.stage("evaluate")
    with pytest.raises(ConfigError, match="a stage is listed twice"):
        resolve_config(None, overrides=['stages=["tokenizer", "tokenizer"]'], host=host)


def test_a_scene_validates_against_the_stages_its_host_registered(make_plugin):
    # Without the plugin that registers the cluster and adapt stages, a scene that runs them does not
    # validate, and the error lists the stages that are registered.
    without = load_plugins(autoload=False, block=["adaptation"])
    assert "cluster" not in without.stages and "adapt" not in without.stages
    for scene in ("few-shot", "zero-shot"):
        with pytest.raises(
            ConfigError,
            match=r"stages: unknown stage 'cluster'; available: fewshot, generator, "
            r"pretrained, reconstruct, render, tokenizer",
        ):
            resolve_config(scene, host=without)
    with pytest.raises(
        ConfigError,
        match=r"stages: unknown stage 'adapt'; available: fewshot, generator, pretrained, "
        r"reconstruct, render, tokenizer",
    ):
        resolve_config("cross-sensor", host=without)
    assert resolve_config("reconstruction", host=without).stages == ["tokenizer", "reconstruct"]

    # A stage registered by a plugin is listed like the built-ins and brings its own section.
    class ProbeSection(Section):
        width: int = Field(4, ge=1)

    @hookimpl
    def vqtouch_register_stages(register):
        register("probe", lambda job: {}, section=ProbeSection, needs=("data.dataset",))

    extended = load_plugins(autoload=False, extra=[make_plugin("probe_plugin", vqtouch_register_stages)])
    config = resolve_config(None, overrides=['stages=["probe"]', "probe.width=7"], host=extended)
    assert config.stages == ["probe"] and config.probe.width == 7
    with pytest.raises(
        ConfigError,
        match=r"invalid configuration: probe.width: Input should be greater than or "
        r"equal to 1 \(got 0\)",
    ):
        resolve_config(None, overrides=['stages=["probe"]', "probe.width=0"], host=extended)
    with pytest.raises(ConfigError, match=r"unknown stage 'probe'; available: adapt, cluster, fewshot, generator"):
        resolve_config(None, overrides=['stages=["probe"]'], host=load_plugins(autoload=False))


def test_resolve_config_needs_the_host_keyword(host):
    with pytest.raises(TypeError, match="host"):
        resolve_config("reconstruction")
    with pytest.raises(TypeError, match="positional"):
        resolve_config("reconstruction", (), (), host)  # the host is keyword-only


def test_validating_a_slot_without_a_host_says_to_pass_it():
    with pytest.raises(ValidationError) as info:
        ExperimentConfig.model_validate({"sensor": {"name": "gelsight"}})
    (error,) = info.value.errors(include_url=False)
    assert error["loc"] == ("sensor",) and error["type"] == "no_plugin_host"
    assert error["msg"].startswith(
        "validating a plugin slot needs the PluginHost whose registries to use: "
        "pass it in the validation context under the key 'host'"
    )
    assert "vqtouch.core.validate_experiment" in error["msg"]
    # Fields that are not slots need no host.
    assert ExperimentConfig.model_validate({"seed": 3}).seed == 3


def test_slot_options_are_validated_at_load_with_exact_path(host):
    with pytest.raises(ConfigError) as info:
        resolve_config("label-to-touch", overrides=["generator.conditioners.0.num_tokens=0"], host=host)
    assert str(info.value) == (
        "invalid configuration: generator.conditioners.0.num_tokens: Input should be greater than or equal to 1 (got 0)"
    )


def test_stage_section_options_are_validated_with_exact_path(host):
    with pytest.raises(ConfigError) as info:
        resolve_config("reconstruction", overrides=["tokenizer.train.steps=-1"], host=host)
    assert str(info.value) == (
        "invalid configuration: tokenizer.train.steps: Input should be greater than or equal to 0 (got -1)"
    )
    with pytest.raises(ConfigError) as info:
        resolve_config("reconstruction", overrides=["render.num_samples=0"], host=host)
    assert str(info.value) == (
        "invalid configuration: render.num_samples: Input should be greater than or equal to 1 (got 0)"
    )
    # The old top-level paths are refused or moved to their new homes (tests/test_deprecations.py): never a
    # misleading "did you mean".
    with pytest.raises(ConfigError, match="config key 'train' .* split into tokenizer.train and generator.train"):
        resolve_config("reconstruction", overrides=["train.steps=3"], host=host)
    with pytest.warns(VqtouchDeprecationWarning, match="'clusterer' was renamed to 'cluster.clusterer'"):
        with pytest.raises(ConfigError, match=r"cluster\.clusterer: unknown clusterer 'x'"):
            resolve_config("reconstruction", overrides=["clusterer.name=x"], host=host)


def test_tokenizer_train_keeps_vqgan_betas_while_core_defaults_to_adamw(host):
    from vqtouch.plugins.training.settings import TrainConfig

    config = resolve_config("reconstruction", host=host)
    assert config.tokenizer.train.betas == (0.5, 0.9)
    assert isinstance(config.tokenizer.train, TrainConfig)
    assert TrainConfig().betas == (0.9, 0.999)


def test_unknown_plugin_lists_choices_and_closest(host):
    with pytest.raises(
        ConfigError,
        match=r"generator.conditioners.0: unknown conditioner 'lable'; available: clip, "
        r"label, sensor, tactile, tactile_codes, text, text_scratch, visual, visual_cnn; "
        r"did you mean 'label'\?",
    ):
        resolve_config("label-to-touch", overrides=["generator.conditioners.0.name=lable"], host=host)


def test_unknown_option_lists_allowed(host):
    with pytest.raises(
        ConfigError,
        match=r"tokenizer.train: unknown option 'step'; allowed: .*steps.*"
        r"did you mean 'steps'",
    ):
        resolve_config("label-to-touch", overrides=["tokenizer.train.step=3"], host=host)


def test_literal_error_lists_allowed_values(host):
    with pytest.raises(ConfigError, match=r"device: Input should be 'auto', 'cpu' or 'cuda' \(got 'tpu'\)"):
        resolve_config("label-to-touch", overrides=["device=tpu"], host=host)


def test_changing_slot_name_resets_its_options(host):
    config = resolve_config(
        "label-to-touch",
        overrides=["generator.conditioners.0.name=tactile", "generator.conditioners.0.width=16"],
        host=host,
    )
    assert config.generator.conditioners[0].model_dump() == {
        "name": "tactile",
        "width": 16,
        "depth": 3,
        "token_grid": 4,
        "spatial": True,
        "grid_context": [],
        "grid_context_width": None,
        "reads": "tactile_source",
    }
    config = resolve_config("reconstruction", overrides=["tokenizer.quantizer.name=ema_vq"], host=host)
    assert "lookup_dim" not in config.tokenizer.quantizer.model_dump()  # the scene's vq options are dropped


def test_slot_given_as_string(host):
    config = resolve_config("label-to-touch", overrides=["generator.conditioners.0=tactile"], host=host)
    assert config.generator.conditioners[0].name == "tactile"
    config = resolve_config(
        "reconstruction", overrides=["cluster.clusterer=null", "tokenizer.quantizer=ema_vq"], host=host
    )
    assert config.tokenizer.quantizer.name == "ema_vq" and config.cluster.clusterer is None


def test_list_slot_set_whole_as_json(host):
    config = resolve_config(
        "reconstruction",
        overrides=['generator.conditioners=[{"name": "label"}, "tactile"]', "generator.conditioners.0.num_tokens=2"],
        host=host,
    )
    assert [item.name for item in config.generator.conditioners] == ["label", "tactile"]
    assert config.generator.conditioners[0].num_tokens == 2


def test_override_values_are_json_or_string():
    assert parse_override("tokenizer.train.steps=5") == (["tokenizer", "train", "steps"], 5)
    assert parse_override("name=my-run") == (["name"], "my-run")
    assert parse_override('metrics=[{"name": "psnr"}]') == (["metrics"], [{"name": "psnr"}])
    for bad in ("tokenizer.train.steps", "=3", "a..b=1"):
        with pytest.raises(ConfigError, match="bad override"):
            parse_override(bad)


def test_list_index_overrides(host):
    config = resolve_config("label-to-touch", overrides=["metrics.1.window_size=7"], host=host)
    assert config.metrics[1].window_size == 7
    with pytest.raises(ConfigError, match="index '5' is not within a list of 4"):
        resolve_config("label-to-touch", overrides=["metrics.5.name=psnr"], host=host)
    with pytest.raises(ConfigError, match="index '1' is not within a list of 1"):
        resolve_config("label-to-touch", overrides=["generator.conditioners.1.num_tokens=2"], host=host)


def test_cannot_descend_into_a_scalar():
    with pytest.raises(ConfigError, match="tokenizer.train.steps is int 3, not a section"):
        apply_override({"tokenizer": {"train": {"steps": 3}}}, ["tokenizer", "train", "steps", "x"], 1)


def test_top_level_name_is_not_a_slot_reset():
    assert apply_override({"name": "a", "seed": 1}, ["name"], "b") == {"name": "b", "seed": 1}


def test_merge_replaces_block_when_plugin_changes():
    base = {"tokenizer": {"quantizer": {"name": "vq", "codebook_size": 2}, "train": {"steps": 1, "learning_rate": 0.1}}}
    merged = merge_configs(base, {"tokenizer": {"quantizer": {"name": "ema_vq"}, "train": {"steps": 2}}})
    assert merged == {"tokenizer": {"quantizer": {"name": "ema_vq"}, "train": {"steps": 2, "learning_rate": 0.1}}}
    assert base["tokenizer"]["train"]["steps"] == 1  # inputs untouched


def test_toml_and_json_files_merge_in_order(host, tmp_path):
    toml_file = tmp_path / "a.toml"
    toml_file.write_text(
        'seed = 7\n[tokenizer.train]\nsteps = 11\n[[generator.conditioners]]\nname = "tactile"\nwidth = 32\n'
    )
    json_file = tmp_path / "b.json"
    json_file.write_text(json.dumps({"tokenizer": {"train": {"learning_rate": 0.01}}}))
    config = resolve_config("label-to-touch", [toml_file, json_file], ["tokenizer.train.steps=12"], host=host)
    assert (config.seed, config.tokenizer.train.steps, config.tokenizer.train.learning_rate) == (7, 12, 0.01)
    assert [c.name for c in config.generator.conditioners] == ["tactile"]
    assert config.generator.conditioners[0].width == 32
    assert config.tokenizer.autoencoder.name == "dm_vqgan"  # the scene's other tokenizer options are kept


@pytest.mark.parametrize(
    "name, text, message",
    [
        ("missing.toml", None, "does not exist"),
        ("bad.toml", "seed = = 1", "cannot parse"),
        ("bad.json", "{", "cannot parse"),
        ("list.json", "[1, 2]", "top level must be a table"),
        ("conf.ini", "x", "unsupported config format '.ini'"),
    ],
)
def test_config_file_errors_name_the_file(host, tmp_path, name, text, message):
    path = tmp_path / name
    if text is not None:
        path.write_text(text)
    with pytest.raises(ConfigError, match=message) as info:
        resolve_config(None, [path], host=host)
    assert name in str(info.value)


def test_multiple_problems_are_reported_together(host):
    with pytest.raises(ConfigError, match=r"\(2 problems\): seed: .*; tokenizer.train.steps: "):
        resolve_config(None, overrides=["seed=-1", "tokenizer.train.steps=-1"], host=host)


def test_required_and_missing_slots(host):
    config = resolve_config("label-to-touch", host=host)
    assert required_slots(config, host) == [
        "data.dataset",
        "tokenizer.autoencoder",
        "tokenizer.quantizer",
        "tokenizer.discriminator",
        "metrics",
        "sensor",
        "generator.model",
        "generator.conditioners",
        "generator.sampler",
    ]
    assert missing_slots(config, host) == []
    no_model = resolve_config("label-to-touch", overrides=["generator.model=null"], host=host)
    assert ("generator", "generator.model") in missing_slots(no_model, host)
    assert all(path != "generator.conditioners" for _, path in missing_slots(config, host))
    # The discriminator is optional: an empty one is never "missing".
    no_disc = resolve_config("label-to-touch", overrides=["tokenizer.discriminator=null"], host=host)
    assert all(path != "tokenizer.discriminator" for _, path in missing_slots(no_disc, host))
    # An empty list slot that a stage needs is missing.
    no_conditioner = resolve_config("label-to-touch", overrides=["generator.conditioners=[]"], host=host)
    assert ("generator", "generator.conditioners") in missing_slots(no_conditioner, host)


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
    with pytest.raises(Exception):
        config.tokenizer.train.steps = 3


def test_switching_a_slots_plugin_after_setting_its_options_is_refused(host):
    # The reset would silently drop channels=32 and train the default width instead.
    with pytest.raises(
        ConfigError,
        match=r"--set tokenizer.autoencoder.name=vqgan selects another plugin for "
        r"tokenizer.autoencoder.*--set tokenizer.autoencoder.channels=32; put",
    ):
        resolve_config(
            "reconstruction",
            overrides=["tokenizer.autoencoder.channels=32", "tokenizer.autoencoder.name=vqgan"],
            host=host,
        )
    with pytest.raises(ConfigError, match="drop the earlier --set tokenizer.quantizer.codebook_size=8"):
        resolve_config(
            "reconstruction",
            overrides=["tokenizer.quantizer.codebook_size=8", 'tokenizer.quantizer={"name": "ema_vq"}'],
            host=host,
        )
    # Name first, options after: both kept.  Re-stating the same plugin resets nothing, so it is allowed.
    config = resolve_config(
        "reconstruction",
        overrides=[
            "tokenizer.autoencoder.name=vqgan",
            "tokenizer.autoencoder.channels=32",
            "tokenizer.autoencoder.name=vqgan",
        ],
        host=host,
    )
    assert config.tokenizer.autoencoder.name == "vqgan" and config.tokenizer.autoencoder.channels == 32


@pytest.mark.parametrize("switch", ["generator.conditioners.0=label", "generator.conditioners.0.name=label"])
def test_switching_a_list_slot_items_plugin_after_setting_its_options_is_refused(host, switch):
    # The item of a list slot (the old top-level `conditioner`) is protected like a single slot.
    with pytest.raises(
        ConfigError,
        match=f"--set {switch} selects another plugin for generator.conditioners.0.*"
        "drop the earlier --set generator.conditioners.0.width=16",
    ):
        resolve_config("touch-to-touch", overrides=["generator.conditioners.0.width=16", switch], host=host)


@pytest.mark.parametrize(
    "override, problem",
    [
        ("data.batch_size=true", "data.batch_size: Input should be a valid integer (got True)"),
        ("data.num_workers=true", "data.num_workers: Input should be a valid integer (got True)"),
        (
            "data.image_size=true",
            "data.image_size: expected a side S (S x S pixels) or [height, width] such as "
            "[240, 320], whole numbers of pixels from 8 to 4096 (got True)",
        ),
        (
            "data.image_size=[240]",
            "data.image_size: expected a side S (S x S pixels) or [height, width] such as "
            "[240, 320], whole numbers of pixels from 8 to 4096 (got [240])",
        ),
        (
            "data.image_size=[4, 320]",
            "data.image_size: expected a side S (S x S pixels) or [height, width] such as "
            "[240, 320], whole numbers of pixels from 8 to 4096 (got [4, 320])",
        ),
        ('data.batch_size="16"', "data.batch_size: Input should be a valid integer (got '16')"),
        ("data.val_fraction=false", "data.val_fraction: Input should be a valid number (got False)"),
    ],
)
def test_data_counts_refuse_booleans_instead_of_reading_them_as_numbers(host, override, problem):
    # In lax mode `true` became batch_size=1 and `false` val_fraction=0: valid, and not what was meant.
    with pytest.raises(ConfigError) as info:
        resolve_config("reconstruction", overrides=[override], host=host)
    assert str(info.value) == f"invalid configuration: {problem}"


def test_data_counts_still_take_plain_numbers(host):
    config = resolve_config(
        "reconstruction",
        overrides=["data.batch_size=4", "data.num_workers=0", "data.image_size=32", "data.val_fraction=0"],
        host=host,
    )
    assert (config.data.batch_size, config.data.num_workers, config.data.image_size) == (4, 0, 32)
    assert config.data.val_fraction == 0.0 and isinstance(config.data.val_fraction, float)


def test_non_utf8_config_file_names_the_file(tmp_path):
    from vqtouch.core.config import load_config_file

    path = tmp_path / "latin1.json"
    path.write_bytes('{"description": "Kraftsensor f\u00fcr Gelsight"}'.encode("latin-1"))
    with pytest.raises(ConfigError) as info:
        load_config_file(path)
    assert str(info.value) == (
        f"{path}: not UTF-8 text (byte 0xfc at position 30); save it as UTF-8 (TOML and JSON config files are UTF-8)"
    )


def _write_recipe(path, scene, steps=7):
    path.write_text(f'scene = "{scene}"\n\n[tokenizer.train]\nsteps = {steps}\n')
    return path


def test_a_recipe_file_brings_its_scene(host, tmp_path):
    """A config file that names its scene is merged over that scene, with no --scene; the same file
    beside another scene is refused in one line naming both."""
    recipe = _write_recipe(tmp_path / "recipe.toml", "label-to-touch")
    by_recipe = resolve_config(None, [recipe], host=host)
    by_scene = resolve_config("label-to-touch", [recipe], host=host)
    assert by_recipe.model_dump() == by_scene.model_dump()
    assert by_recipe.scene == "label-to-touch" and by_recipe.tokenizer.train.steps == 7
    assert by_recipe.model_dump() != resolve_config("reconstruction", host=host).model_dump()
    with pytest.raises(ConfigError, match="recipe over scene 'label-to-touch', but scene 'reconstruction'") as error:
        resolve_config("reconstruction", [recipe], host=host)
    assert "\n" not in str(error.value)


def test_a_recipe_replaces_the_commands_default_scene_on_the_command_line(tmp_path, capsys):
    """`vqtouch config show --config RECIPE` (no scene named) and a training command's default scene:
    the recipe's scene wins over the default, never over a scene the user named."""
    from vqtouch.plugins.cli.app import main

    recipe = _write_recipe(tmp_path / "recipe.toml", "touch-to-touch", steps=3)
    assert main(["config", "show", "--config", str(recipe)]) == 0
    shown = json.loads(capsys.readouterr().out)
    assert shown["scene"] == "touch-to-touch" and shown["tokenizer"]["train"]["steps"] == 3
    assert main(["config", "show"]) == 2 and "name a scene" in capsys.readouterr().err
    assert main(["config", "show", "label-to-touch", "--config", str(recipe)]) == 2
    assert "recipe over scene 'touch-to-touch'" in capsys.readouterr().err

"""Model only what a scene requires: heavy optional modules are imported only when needed.

Each check runs in a fresh interpreter, since sys.modules of the test process is shared.
"""

import subprocess
import sys

HEAVY = ("open_clip", "torchvision.models", "timm")


def _modules_after(code: str) -> set[str]:
    probe = code + "\nimport sys\nprint('HEAVY:' + ','.join(m for m in {heavy!r} if m in sys.modules))".format(heavy=HEAVY)
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=300,
                            env={"VQTOUCH_DISABLE_PLUGIN_AUTOLOAD": "1", "PATH": "/usr/bin:/bin"})
    assert result.returncode == 0, result.stderr[-2000:]
    last = result.stdout.strip().splitlines()[-1]
    assert last.startswith("HEAVY:"), result.stdout
    return set(filter(None, last.removeprefix("HEAVY:").split(",")))


def test_importing_vqtouch_and_loading_plugins_imports_no_heavy_model_code():
    code = ("import vqtouch, vqtouch.core, vqtouch.plugins, vqtouch.conditioners, vqtouch.sensors\n"
            "host = vqtouch.core.load_plugins()\n"
            "import vqtouch.core.cli; vqtouch.core.cli.build_parser(host)")
    assert _modules_after(code) == set()


def test_label_conditioned_run_never_imports_open_clip():
    code = ("from vqtouch.core import load_plugins, resolve_config, build_components, BuildContext\n"
            "host = load_plugins()\n"
            "config = resolve_config('label-to-touch', host=host)\n"
            "built = build_components(config, host, slots=['conditioner', 'metrics'], "
            "context=BuildContext(num_classes=3))\n"
            "assert type(built['conditioner']).__name__ == 'LabelConditioner'")
    assert "open_clip" not in _modules_after(code)


def test_vision_scene_imports_open_clip_only_when_the_conditioner_is_built():
    code = ("from vqtouch.core import load_plugins, resolve_config, MissingWeightsError\n"
            "host = load_plugins()\n"
            "config = resolve_config('vision-to-touch', host=host)\n"
            "assert config.conditioner.name == 'clip'")
    assert _modules_after(code) == set()


def test_build_components_builds_only_required_slots():
    from vqtouch.core import BuildContext, build_components, load_plugins, resolve_config

    host = load_plugins(autoload=False)
    config = resolve_config("reconstruction", overrides=["conditioner=tactile"], host=host)
    # The reconstruction scene has no generator stage: a conditioner set by mistake is not built.
    assert "conditioner" not in config.required_slots()
    built = build_components(config, host, slots=[s for s in config.required_slots() if s == "metrics"],
                             context=BuildContext())
    assert list(built) == ["metrics"]


def test_missing_required_slot_names_stage_and_choices():
    import pytest

    from vqtouch.core import ConfigError, build_components, load_plugins, resolve_config

    host = load_plugins(autoload=False)
    config = resolve_config("label-to-touch", host=host)
    with pytest.raises(ConfigError, match=r"stage 'generator' needs generator .* set generator.name to one of: "
                                          r"none installed yet"):
        build_components(config, host)
    emptied = resolve_config("label-to-touch", overrides=["tokenizer.encoder=null"], host=host)
    with pytest.raises(ConfigError, match=r"stage 'tokenizer' needs tokenizer.encoder .* one of: dm_vqgan, .*vqgan"):
        build_components(emptied, host)

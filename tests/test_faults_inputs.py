"""Fault injection on what commands read back and on how they speak: files validated in one line,
paths kept inside their folders, bounded threads, a closed stdout, messages that name the option the
user typed and advice that names a flag that exists, and conditioner keys checked before anything runs."""

from __future__ import annotations

import json
import subprocess
import sys
import types
import warnings
from pathlib import Path

import pytest
import torch

import generator_runs
from cli_checks import one_error_line, snapshot

from vqtouch.core import ConfigError, DatasetError, VqtouchDeprecationWarning, load_plugins
from vqtouch.plugins.runtime.run_dir import RunDir
from vqtouch.plugins.cli.app import main
from vqtouch.plugins.utils.images import save_png

HOST = load_plugins()


@pytest.fixture(scope="module")
def tokenizer_folder(tmp_path_factory):
    return generator_runs.tiny_tokenizer_folder(tmp_path_factory.mktemp("tok"))


def _image_folder(folder: Path, count: int = 6, size: int = 32) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    generator = torch.Generator().manual_seed(0)
    for index in range(count):
        save_png(torch.rand(3, size, size, generator=generator), folder / f"{index:03d}.png")
    return folder


# -- 6. every file read back is validated -----------------------------------------------------------------------


def _families_folder(tmp_path: Path, **changes) -> Path:
    folder = tmp_path / "families"
    folder.mkdir()
    summary = {
        "tokenizer": "tok",
        "features": "pooled",
        "image_size": 32,
        "refine_steps": 0,
        "keep": 1.0,
        "refusal_threshold": 0.5,
        "clusterer": {"name": "kmeans"},
        "sensors": [{"name": "a", "source": "gelsight"}, {"name": "b", "source": "digit"}],
        "families": [["a"], ["b"]],
        "sensor_family": {"a": 0, "b": 1},
        "prototypes": {"a": [0.0, 1.0], "b": [1.0, 0.0]},
    } | changes
    (folder / "cluster.json").write_text(json.dumps(summary))
    (folder / "clusterer.safetensors").write_bytes(b"never read: the JSON is refused first")
    return folder


@pytest.mark.parametrize(
    "changes, field",
    [
        ({"sensors": "gelsight"}, "sensors: input should be a valid list"),
        ({"refusal_threshold": "NaN"}, "refusal_threshold: input should be a valid number (got 'NaN')"),
        ({"sensor_family": {"a": 0, "b": 7}}, "sensor 'b' is in family 7, which is not listed"),
        ({"prototypes": {"a": [0.0]}}, "sensor 'b' has no prototype or family"),
    ],
)
def test_a_hand_edited_cluster_json_is_one_line_naming_the_file_and_field(tmp_path, changes, field):
    from vqtouch.plugins.adaptation.families import load_families

    folder = _families_folder(tmp_path, **changes)
    with pytest.raises(ConfigError) as caught:
        load_families(folder, HOST)
    message = str(caught.value)
    assert message.startswith(f"{folder / 'cluster.json'}: ") and field in message and "\n" not in message


@pytest.mark.parametrize(
    "stages, field",
    [
        ([3], "stages.0: input should be a valid dictionary"),
        ([{"stage": "tokenizer", "seconds": "fast"}], "stages.0.seconds: input should be a valid number"),
        ([{"stage": "tokenizer", "seconds": float("nan")}], "stages.0.seconds: input should be a finite number"),
        ([{"stage": "tokenizer", "result": "x"}], "stages.0.result: input should be a valid dictionary"),
    ],
)
def test_a_damaged_report_json_is_one_line(tmp_path, capsys, stages, field):
    run = tmp_path / "run"
    run.mkdir()
    (run / "report.json").write_text(json.dumps({"scene": "tour", "stages": stages}))
    assert main(["report", str(run), "--out", str(tmp_path / "page")]) == 2
    assert one_error_line(capsys).startswith(f"{run / 'report.json'}: {field}")


def test_the_report_embeds_only_pictures_inside_the_run(tmp_path):
    from vqtouch.plugins.report.html import render_html

    run, outside = tmp_path / "run", tmp_path / "secret.png"
    run.mkdir()
    save_png(torch.rand(3, 8, 8), outside)
    save_png(torch.rand(3, 8, 8), run / "own.png")
    result = {"picture": "own.png", "pictures": {str(outside): "elsewhere", "../secret.png": "above"}}
    page = render_html({"scene": "tour", "stages": [{"stage": "x", "status": "ran", "result": result}]}, run)
    assert page.count("data:image/png;base64,") == 1
    assert page.count("is outside the run folder") == 2


@pytest.mark.parametrize("row", ["../outside.png", "ABSOLUTE"])
def test_an_index_row_outside_its_folder_is_refused_unless_allowed(tmp_path, row):
    folder = _image_folder(tmp_path / "frames")
    outside = _image_folder(tmp_path / "elsewhere", count=1) / "000.png"
    (tmp_path / "outside.png").write_bytes(outside.read_bytes())
    row = str(outside) if row == "ABSOLUTE" else row
    (folder / "index.csv").write_text(f"path,label\n000.png,0\n{row},0\n")
    options = {"name": "image_folder", "root": str(folder), "csv": "index.csv", "image_size": 32}
    with pytest.raises(DatasetError, match=rf"index.csv line 3: '{row}' is outside {folder}; .*paths_outside=true"):
        HOST.build("dataset", options)
    assert len(HOST.build("dataset", options | {"paths_outside": True})) == 2


def test_a_products_index_naming_a_file_outside_the_run_is_refused(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "products.json").write_text(json.dumps({"families": {"stage": "cluster", "path": "../../etc"}}))
    with pytest.raises(ConfigError, match=r"products.json: '../../etc' is outside"):
        RunDir(run).products()
    (run / "products.json").write_text(json.dumps({"families": {"stage": 3, "path": "x"}}))
    with pytest.raises(ConfigError, match=r"product 'families'\): stage: input should be a valid string"):
        RunDir(run).products()


def test_an_adapt_json_and_a_fewshot_json_are_validated(tmp_path):
    from vqtouch.plugins.experiments.fewshot_generation import adapted_summary
    from vqtouch.plugins.experiments.fewshot_table import finished_arm

    (tmp_path / "adapt.json").write_text(json.dumps({"adapted_from": 3}))
    with pytest.raises(ConfigError, match=r"adapt.json: target: field required"):
        adapted_summary(tmp_path, tmp_path)
    (tmp_path / "fewshot.json").write_text(json.dumps({"images": "x", "shots": "4", "ratio": 1, "seed": 0}))
    with pytest.raises(ConfigError, match=r"fewshot.json: shots: input should be a valid integer"):
        finished_arm(tmp_path, {"shots": 4})


# -- 7. crashes without a word ---------------------------------------------------------------------------------


def test_threads_beyond_the_machine_are_refused_in_one_line(monkeypatch, capsys):
    assert main(["--threads", "99999999", "config", "scenes"]) == 2
    assert one_error_line(capsys).startswith("--threads 99999999: at most ")
    monkeypatch.setenv("VQTOUCH_THREADS", "100000")
    assert main(["config", "scenes"]) == 2
    assert one_error_line(capsys).startswith("VQTOUCH_THREADS='100000': at most ")


def test_a_closed_stdout_is_not_a_traceback():
    done = subprocess.run(
        f"{sys.executable} -m vqtouch.plugins.cli config scenes >&-",
        shell=True,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr


# -- 8. messages name the option typed; advice names a flag that exists ----------------------------------------


@pytest.mark.parametrize(
    "command",
    [["fewshot"], ["evaluate", "fewshot-generation"], ["evaluate", "mix-ratio"], ["reconstruct"], ["adapt"]],
    ids=" ".join,
)
def test_every_command_that_reads_image_folders_takes_the_flags_its_messages_advise(command, capsys):
    main([*command, "--help"])
    usage = capsys.readouterr().out
    assert "--allow-greyscale" in usage and "--lenient" in usage


def test_a_flat_folder_with_greyscale_or_broken_frames_has_a_way_in(tokenizer_folder, tmp_path, capsys):
    from PIL import Image

    folder = _image_folder(tmp_path / "frames")
    Image.new("L", (32, 32), 128).save(folder / "006.png")
    reconstruct = ["reconstruct", "--run", str(tokenizer_folder), "--images", str(folder)]
    assert main([*reconstruct, "--out", str(tmp_path / "a")]) == 2
    assert "pass --allow-greyscale (commands that read images)" in one_error_line(capsys)
    assert main([*reconstruct, "--out", str(tmp_path / "a"), "--allow-greyscale"]) == 0
    assert json.loads((tmp_path / "a" / "reconstruct.json").read_text())["images"] == 7
    (folder / "007.png").write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    assert main([*reconstruct, "--out", str(tmp_path / "b"), "--allow-greyscale"]) == 2
    assert one_error_line(capsys).endswith("pass --lenient to skip the images that cannot be used")
    capsys.readouterr()
    assert main([*reconstruct, "--out", str(tmp_path / "b"), "--allow-greyscale", "--lenient"]) == 0
    assert "vqtouch: warning: " in capsys.readouterr().err
    assert json.loads((tmp_path / "b" / "reconstruct.json").read_text())["images"] == 7
    assert main([*reconstruct, "--out", str(tmp_path / "c"), "--images-option", "lenient=true"]) == 2
    assert "(--lenient and --allow-greyscale work on such a folder)" in one_error_line(capsys)


def test_the_shots_of_mix_ratio_are_named_as_typed(family_tokenizer_run, tmp_path, capsys):
    folder = _image_folder(tmp_path / "frames")
    assert main(["evaluate", "mix-ratio", "--run", str(family_tokenizer_run), "--target", str(folder), "--shots", "50",
                 "--out", str(tmp_path / "out")]) == 2  # fmt: skip
    assert one_error_line(capsys).startswith(
        f"--shots 50: the folder {folder} holds 6 images; the largest usable --shots is 5"
    )


def test_a_ratio_that_would_render_billions_of_images_is_refused_by_its_name(capsys):
    assert main(["fewshot", "--run", "r", "--images", "gelsight", "--out", "o", "--ratio", "1e9"]) == 2
    assert "--ratio: 1e9: must be a finite number in [0, 1000]" in capsys.readouterr().err


def test_an_empty_text_and_a_rank_without_candidates_are_refused(tmp_path, capsys):
    generate = ["generate", "--run", "pretrained:tour", "--out", str(tmp_path / "g")]
    assert main([*generate, "--text", ""]) == 2
    assert (
        one_error_line(capsys) == "--text '': an empty condition; give one, e.g. --text 'a ball pressed into the gel'"
    )
    assert main([*generate, "--label", "knurl", "--best-of-rank", "consensus"]) == 2
    assert one_error_line(capsys).startswith("--best-of-rank consensus ranks --best-of's candidates, and one draw")
    assert not (tmp_path / "g").exists()


def test_a_librarys_warning_is_one_vqtouch_line_without_its_source(capsys):
    from vqtouch.plugins.cli.errors import _show_warning

    _show_warning(UserWarning("constrained_layout not applied because axes sizes collapsed"), UserWarning,
                  "/site-packages/matplotlib/figure.py", 3500, line="    warnings.warn(...)")  # fmt: skip
    err = capsys.readouterr().err
    assert err == (
        "vqtouch: warning: constrained_layout not applied because axes sizes collapsed (UserWarning from figure)\n"
    )


# -- 9. a conditioner's sample keys are checked before anything runs -------------------------------------------


@pytest.fixture
def old_material_plugin(monkeypatch):
    """A conditioner written against 0.1.0: ``modality = "material"``, a key no built-in dataset has."""
    from typing import Literal

    from vqtouch.core import Conditioner, PluginConfig, hookimpl

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", VqtouchDeprecationWarning)

        class MaterialConfig(PluginConfig):
            """Options of the material conditioner."""

            name: Literal["material"] = "material"

        class Material(Conditioner):
            modality = "material"

            def encode(self, condition):
                return self.null_tokens_ND.expand(len(condition), -1, -1)

    @hookimpl
    def vqtouch_register_conditioners(register):
        register("material", lambda config, context: Material(context.cond_dim, 1), MaterialConfig)

    module = types.ModuleType("old_material_plugin")
    module.vqtouch_register_conditioners = vqtouch_register_conditioners
    monkeypatch.setitem(sys.modules, "old_material_plugin", module)
    monkeypatch.setenv("VQTOUCH_PLUGINS", "old_material_plugin")
    return module


def test_a_conditioner_that_reads_a_key_the_dataset_lacks_is_refused_before_a_run_exists(
    old_material_plugin, tmp_path, capsys
):
    out = tmp_path / "run"
    conditioners = '--set=generator.conditioners=[{"name": "material"}]'
    assert main([*generator_runs.train_args(out), conditioners]) == 2
    message = one_error_line(capsys)
    assert message.startswith("conditioner 'material' (plugin 'old_material_plugin') reads the samples' 'material', ")
    assert "which dataset 'procedural' does not provide (its samples have " in message
    assert not out.exists()
    demo = ["demo", "--scene", "label-to-touch", "--out", str(tmp_path / "demo"), conditioners]
    assert main(demo) == 2
    assert one_error_line(capsys).startswith("conditioner 'material' (plugin 'old_material_plugin') reads")
    assert not (tmp_path / "demo").exists()
    assert snapshot(tmp_path) == {}

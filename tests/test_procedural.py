"""The embedded procedural dataset and `vqtouch data render`."""

import csv
import json

import pytest
import torch

from vqtouch.core import Assembly, BuildContext, ConfigError, load_plugins, resolve_config
from vqtouch.plugins.cli.app import main
from vqtouch.sensors.objects import CLASS_NAMES, OBJECT_CLASSES, sample_contact

HOST = load_plugins(autoload=False)


def make_sensor(config="gelsight"):
    return HOST.build("sensor_family", config)


def dataset(sensor_config="gelsight", context=None, **options):
    """The procedural dataset outside an experiment: the caller supplies the sensor that renders it."""
    return HOST.build(
        "dataset",
        {"name": "procedural", "num_samples": 24, "image_size": 32, **options},
        context or BuildContext(),
        sensor=make_sensor(sensor_config),
    )


def test_at_least_twelve_labelled_classes_with_materials():
    assert len(OBJECT_CLASSES) >= 12 and len(set(CLASS_NAMES)) == len(CLASS_NAMES)
    assert len({c.material for c in OBJECT_CLASSES}) >= 10


def test_the_light_plugin_module_names_the_scene_library_classes_in_order():
    from vqtouch.plugins.data import procedural_plugin

    assert procedural_plugin.CLASS_NAMES == CLASS_NAMES


@pytest.mark.parametrize("index", range(len(OBJECT_CLASSES)))
def test_every_class_makes_a_real_contact_no_deeper_than_asked(index):
    generator = torch.Generator().manual_seed(index)
    contact = sample_contact(OBJECT_CLASSES[index], index, generator, 48, 14.0, (0.3, 0.6))
    assert torch.isfinite(contact.surface_mm_HW).all()
    assert contact.indentation_mm_HW.max() == pytest.approx(contact.depth_mm, abs=1e-4)
    assert contact.depth_mm <= 0.6 + 1e-6
    assert 0 < (contact.indentation_mm_HW > 0).float().mean() < 1  # touches part, not none, of the view


def test_samples_follow_the_contract():
    data = dataset()
    sample = data[5]
    assert sample["tactile"].shape == sample["visual"].shape == (3, 32, 32)
    for key in ("tactile", "visual"):
        assert sample[key].dtype == torch.float32 and 0 <= sample[key].min() and sample[key].max() <= 1
    assert 0 <= sample["label"] < data.num_classes == 12
    assert data.class_names[sample["label"]].replace("_", " ") in sample["text"] or "digit" in sample["text"]
    assert sample["sensor"] == "gelsight" and sample["id"] == "0-0000005"


def test_deterministic_by_seed_and_independent_of_access_order():
    forward = [dataset(cache=False)[i]["tactile"] for i in (3, 7)]
    backward = [dataset(cache=False)[i]["tactile"] for i in (7, 3)][::-1]
    for a, b in zip(forward, backward):
        assert torch.equal(a, b)
    assert not torch.equal(dataset(seed=1, cache=False)[3]["tactile"], forward[0])


def test_batch_render_equals_single_samples_even_with_sensor_noise():
    data = dataset({"name": "digit", "variant": {"noise_std": 0.05}}, cache=False)
    batch = data.render_batch([2, 9, 4])
    for row, index in enumerate([2, 9, 4]):
        assert torch.equal(batch["tactile"][row], data[index]["tactile"])
        assert torch.equal(batch["visual"][row], data[index]["visual"])


def test_cache_stores_8_bit_images():
    data = dataset(cache=True)
    first = data[1]
    assert torch.allclose(first["tactile"], dataset(cache=False)[1]["tactile"], atol=0.5 / 255 + 1e-6)
    assert torch.equal(data[1]["tactile"], first["tactile"])


def appearance(image: torch.Tensor) -> torch.Tensor:
    """Colour (mean, spread) and texture (mean absolute neighbour differences) of an image."""
    return torch.cat(
        [
            image.mean(dim=(1, 2)),
            image.std(dim=(1, 2)),
            (image[:, :, 1:] - image[:, :, :-1]).abs().mean(dim=(1, 2)),
            (image[:, 1:] - image[:, :-1]).abs().mean(dim=(1, 2)),
        ]
    )


def test_visual_appearance_differs_by_material():
    data = dataset(num_samples=240, image_size=32, cache=False)
    features = {}
    for index in range(240):
        sample = data[index]
        features.setdefault(sample["label"], []).append(appearance(sample["visual"]))
    per_class = torch.stack([torch.stack(v).mean(0) for _, v in sorted(features.items())])
    assert len(features) == 12
    assert torch.cdist(per_class, per_class).fill_diagonal_(1).min() > 0.02


def test_class_filter_and_errors():
    data = dataset(classes=["sphere", "weave"])
    assert data.class_names == ["sphere", "weave"] and {data[i]["label"] for i in range(24)} <= {0, 1}
    with pytest.raises(ConfigError, match="unknown object classes \\['spere'\\]"):
        dataset(classes=["spere"])
    with pytest.raises(ConfigError, match="depth_mm"):
        dataset(depth_mm=(1.0, 0.5))
    with pytest.raises(IndexError, match="out of range"):
        dataset()[24]


def test_image_size_comes_from_the_experiment_when_unset():
    data = dataset(context=BuildContext(image_size=40), num_samples=2, image_size=None)
    assert data[0]["tactile"].shape == (3, 40, 40)
    # Inside an experiment the context comes from data.image_size.
    config = resolve_config("reconstruction", overrides=["data.image_size=24", "data.dataset.num_samples=2"], host=HOST)
    assert Assembly(config, HOST).component("data.dataset")[0]["tactile"].shape == (3, 24, 24)


def test_the_sensor_is_an_input_not_an_option():
    with pytest.raises(
        ConfigError,
        match=r"dataset: unknown option 'sensor'; allowed: cache, classes, depth_mm, "
        r"image_size, name, num_samples, seed",
    ):
        HOST.build("dataset", {"name": "procedural", "sensor": {"name": "digit"}}, sensor=make_sensor())
    with pytest.raises(
        ConfigError,
        match=r"dataset 'procedural' needs sensor: build it through the experiment's "
        r"Assembly .* or pass sensor=\.\.\.",
    ):
        HOST.build("dataset", {"name": "procedural", "num_samples": 2})
    assert HOST.registry("dataset").get("procedural").inputs == ("sensor",)


def test_an_experiment_renders_with_its_own_sensor():
    config = resolve_config(
        None,
        overrides=[
            'data.dataset={"name": "procedural", "num_samples": 3}',
            "data.image_size=16",
            "sensor=digit",
            "target_sensor=gelsight_mini",
        ],
        host=HOST,
    )
    assembly = Assembly(config, HOST)
    data = assembly.component("data.dataset")
    assert data is assembly.component("data.dataset")  # built once per experiment
    assert data.sensor is assembly.sensor("source") and data[0]["sensor"] == "digit"
    # The same scenes rendered by the target sensor (a separate, uncached dataset).
    target = assembly.dataset(sensor_role="target")
    assert target is not data and target.sensor is assembly.sensor("target")
    assert target[0]["sensor"] == "gelsight_mini" and target[0]["label"] == data[0]["label"]
    assert target[0]["tactile"].shape == data[0]["tactile"].shape == (3, 16, 16)


def test_a_paired_sensor_renders_the_same_contacts_and_changes_nothing_else():
    overrides = ['data.dataset={"name": "procedural", "num_samples": 4}', "data.image_size=32", "sensor=digit"]
    single = Assembly(resolve_config(None, overrides=overrides, host=HOST), HOST).component("data.dataset")
    assembly = Assembly(resolve_config(None, overrides=[*overrides, "paired_sensor=gelsight"], host=HOST), HOST)
    paired = assembly.component("data.dataset")
    assert paired.paired_sensor is assembly.sensor("paired") and single.paired_sensor is None
    for index in range(4):
        one, two = single[index], paired[index]
        assert "tactile_source" not in one and two["tactile_source"].shape == (3, 32, 32)
        assert two["sensor"] == "digit" and two["source_sensor"] == "gelsight"
        # Adding the pair leaves the sample's own entries exactly as they were.
        assert all(
            torch.equal(one[key], two[key]) if isinstance(one[key], torch.Tensor) else one[key] == two[key]
            for key in one
        )
        # The pair is GelSight's own rendering: its no-contact border is GelSight's background, not DIGIT's.
        assert not torch.allclose(two["tactile_source"], two["tactile"], atol=0.05)
    # Rendered on demand, cached, and the same in a fresh dataset: a pure function of (seed, index).
    again = Assembly(resolve_config(None, overrides=[*overrides, "paired_sensor=gelsight"], host=HOST), HOST).component(
        "data.dataset"
    )
    assert torch.equal(again[2]["tactile_source"], paired[2]["tactile_source"])
    # The cache keeps 8-bit images: a batch render differs from the cached sample by rounding only.
    assert (paired.render_batch([2])["tactile_source"][0] - paired[2]["tactile_source"]).abs().max() <= 0.5 / 255 + 1e-6


def test_reframing_a_press_matches_the_press_drawn_on_the_other_sensors_grid():
    """A 3 mm ball pressed 1 mm, drawn on a 16 mm grid and reframed to 12 mm, against the same ball
    drawn directly on the 12 mm grid (closed form): equal up to interpolation error at the rim."""
    from vqtouch.plugins.data.procedural import reframe_indentation

    def ball(field_mm, size=64, radius=3.0, depth=1.0, centre=(1.5, -2.0)):
        axis = (torch.arange(size) + 0.5) / size * field_mm - field_mm / 2
        ys, xs = torch.meshgrid(axis, axis, indexing="ij")
        cap = (radius**2 - (xs - centre[0]) ** 2 - (ys - centre[1]) ** 2).clamp_min(0).sqrt()
        return (cap - (radius - depth)).clamp_min(0)[None]

    reframed = reframe_indentation(ball(16.0), 16.0, 12.0)
    direct = ball(12.0)
    assert (reframed - direct).abs().mean() < 0.01 and (reframed - direct).abs().max() < 0.15
    assert abs(float(reframed.sum() - direct.sum())) / float(direct.sum()) < 0.02
    assert torch.equal(reframe_indentation(ball(16.0), 16.0, 16.0), ball(16.0))


def test_a_dataset_built_without_an_experiment_takes_the_paired_sensor_as_an_input():
    data = HOST.build(
        "dataset",
        {"name": "procedural", "num_samples": 2, "image_size": 16},
        BuildContext(),
        sensor=make_sensor("digit"),
        paired_sensor=make_sensor("gelsight_mini"),
    )
    assert data[0]["source_sensor"] == "gelsight_mini" and data[0]["tactile_source"].shape == (3, 16, 16)
    with pytest.raises(
        Exception,
        match=r"dataset 'procedural' takes no input 'camera' \(it declares \['sensor', "
        r"'paired_sensor'\]\)",
    ):
        HOST.build("dataset", {"name": "procedural", "num_samples": 2}, sensor=make_sensor(), camera=make_sensor())


def test_an_experiment_without_a_sensor_fails_in_one_line():
    config = resolve_config(None, overrides=['data.dataset={"name": "procedural", "num_samples": 3}'], host=HOST)
    assert config.sensor is None
    with pytest.raises(ConfigError) as info:
        Assembly(config, HOST).component("data.dataset")
    message = str(info.value)
    assert "\n" not in message and message == (
        "this run needs sensor, which the config leaves empty; choose with "
        "--set sensor.name=<digit|gelsight|gelsight_mini>"
    )
    with pytest.raises(
        ConfigError,
        match=r"this run needs target_sensor, which the config leaves empty; choose with "
        r"--set target_sensor.name=<digit\|gelsight\|gelsight_mini>",
    ):
        Assembly(config, HOST).sensor_config("target")


def test_render_stage_writes_the_experiments_data_rendered_by_its_sensor(tmp_path):
    from vqtouch.plugins.runtime.execution import run_stage
    from vqtouch.plugins.runtime.run_dir import RunDir

    config = resolve_config(
        None,
        overrides=[
            'stages=["render"]',
            "sensor=digit",
            "data.image_size=16",
            'data.dataset={"name": "procedural", "num_samples": 5}',
            "render.num_samples=3",
            "render.folder=scenes",
        ],
        host=HOST,
    )
    run = RunDir.create(config, host=HOST, path=tmp_path / "run")
    outcome = run_stage("render", Assembly(config, HOST), run)
    assert outcome.status == "ran", outcome.describe()
    assert outcome.result["samples"] == 3 and outcome.result["picture"] == "scenes/preview.png"
    rows = list(csv.DictReader(open(run.path / "scenes" / "index.csv")))
    assert len(rows) == 3 and {row["sensor"] for row in rows} == {"digit"}
    assert json.loads((run.path / "scenes" / "render.json").read_text())["dataset"]["num_samples"] == 5
    # Without a dataset the stage cannot run, and says which slot to fill.
    empty = resolve_config(None, overrides=['stages=["render"]', "sensor=digit"], host=HOST)
    outcome = run_stage("render", Assembly(empty, HOST), RunDir.create(empty, host=HOST, path=tmp_path / "empty"))
    assert outcome.status == "unavailable"
    assert outcome.describe().startswith(
        "cannot run: needs data.dataset, which the config leaves empty; choose with --set data.dataset.name=<"
    )


@pytest.mark.parametrize(
    "sensor",
    [
        "gelsight",
        "gelsight_mini",
        "digit",
        '{"name": "gelsight", "variant": {"colour_gain": [1.2, 1, 0.8], "wear_blur": 0.02,'
        ' "noise_std": 0.02, "seed": 5}}',
    ],
)
def test_data_render_writes_a_browsable_folder_readable_back(tmp_path, capsys, sensor):
    out = tmp_path / "render"
    assert (
        main(
            [
                "data",
                "render",
                "--sensor",
                sensor,
                "--n",
                "6",
                "--out",
                str(out),
                "--image-size",
                "32",
                "--batch-size",
                "4",
            ]
        )
        == 0
    )
    assert "wrote 6 samples" in capsys.readouterr().out
    rows = list(csv.DictReader(open(out / "index.csv")))
    assert len(rows) == 6 and set(rows[0]) >= {"path", "label", "visual", "class_name", "text", "sensor"}
    sensor_config = json.loads(sensor) if sensor.startswith("{") else {"name": sensor}
    record = json.loads((out / "render.json").read_text())
    assert (out / "preview.png").is_file() and record["samples"] == 6
    # render.json records the sensor on its own (the dataset's options no longer name one).
    assert record["sensor"] == HOST.validate("sensor_family", sensor_config).model_dump(mode="json")
    assert record["dataset"]["name"] == "procedural" and "sensor" not in record["dataset"]
    assert {row["sensor"] for row in rows} == {sensor_config["name"]}
    # The export is an ordinary image-folder dataset: read it back and compare with the source samples.
    exported = HOST.build("dataset", {"name": "image_folder", "root": str(out), "csv": "index.csv", "image_size": 32})
    source = dataset(sensor_config, num_samples=6, cache=False)
    for index in range(6):
        back, original = exported[index], source[index]
        assert back["label"] == original["label"]
        assert (back["tactile"] - original["tactile"]).abs().max() <= 1 / 255 + 1e-6
        assert (back["visual"] - original["visual"]).abs().max() <= 1 / 255 + 1e-6


def test_data_render_refuses_to_overwrite(tmp_path, capsys):
    (tmp_path / "keep.txt").write_text("x")
    assert main(["data", "render", "--n", "1", "--out", str(tmp_path)]) == 2
    assert "exists and is not empty" in capsys.readouterr().err


def test_data_fidelity_writes_pictures_and_numbers(tmp_path, capsys):
    assert (
        main(["data", "fidelity", "--out", str(tmp_path), "--sensors", "gelsight", "--height", "120", "--crop", "32"])
        == 0
    )
    assert "gelsight       SSIM" in capsys.readouterr().out
    assert (tmp_path / "real_vs_rendered_gelsight.png").is_file()
    assert json.loads((tmp_path / "fidelity.json").read_text())[0]["sensor"] == "gelsight"

"""Sensor families from tokenizer features and `vqtouch cluster`: features against
independent computations, the refined prototype's closed form, families recovered end to end on
rendered sensors and a folder of images, and one-line errors."""

import json

import pytest
import torch

import generator_runs
from vqtouch.core import load_plugins
from vqtouch.plugins.cli.app import main
from vqtouch.plugins.adaptation.families import (
    assign_to_family,
    image_features,
    refusal_threshold,
    sensor_prototype,
    within_family_spread,
)

HOST = load_plugins(autoload=False)


@pytest.fixture(scope="module")
def tokenizer_folder(tmp_path_factory):
    return generator_runs.tiny_tokenizer_folder(tmp_path_factory.mktemp("tok"))


@pytest.fixture(scope="module")
def tokenizer(tokenizer_folder):
    from vqtouch.plugins.tokenizer import load_tokenizer

    return load_tokenizer(tokenizer_folder, HOST)[0]


def test_the_prototype_drops_the_farthest_images_and_is_the_mean_of_the_rest():
    inliers = torch.tensor(
        [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0], [0.5, 0.5], [0.2, 0.8], [0.8, 0.2], [0.5, 0.4]],
        dtype=torch.float64,
    )
    outliers = torch.tensor([[40.0, 40.0], [-30.0, 50.0]], dtype=torch.float64)
    features = torch.cat([inliers, outliers])
    torch.testing.assert_close(sensor_prototype(features, refine_steps=0), features.mean(dim=0))
    torch.testing.assert_close(sensor_prototype(features, refine_steps=3, keep=0.8), inliers.mean(dim=0))
    torch.testing.assert_close(sensor_prototype(features[:1], refine_steps=3), features[0])
    with pytest.raises(ValueError, match=r"keep must lie in \(0, 1\]"):
        sensor_prototype(features, keep=0.0)


def test_assignment_names_the_nearest_family_its_margin_and_refuses_a_far_sensor():
    prototypes = torch.tensor([[0.0, 0.0], [0.2, 0.0], [10.0, 0.0], [10.0, 0.4]], dtype=torch.float64)
    clusterer = HOST.build("clusterer", {"name": "kmeans", "num_families": 2})
    labels = clusterer.fit(prototypes)
    assert labels.tolist() == [0, 0, 1, 1]
    spreads = within_family_spread(prototypes, labels, clusterer.centroids_KF)
    assert spreads == pytest.approx([0.1, 0.2])
    # max(3 x the largest spread, half the distance between the family means (0.1, 0) and (10, 0.2))
    threshold = refusal_threshold(spreads, clusterer.centroids_KF)
    assert threshold == pytest.approx(max(3 * 0.2, (9.9**2 + 0.2**2) ** 0.5 / 2))
    assert refusal_threshold([1.0, 2.0], clusterer.centroids_KF) == pytest.approx(6.0)
    near = assign_to_family(clusterer, torch.tensor([9.0, 1.0]), threshold)
    expected = [(9.0 - 0.1) ** 2 + 1.0, 1.0 + 0.8**2]
    assert near["family"] == near["nearest_family"] == 1 and not near["refused"]
    assert near["distances"] == pytest.approx([e**0.5 for e in expected], abs=1e-6)
    assert near["margin"] == pytest.approx(expected[0] ** 0.5 - expected[1] ** 0.5, abs=1e-6)
    far = assign_to_family(clusterer, torch.tensor([5.0, 40.0]), threshold)
    assert far["refused"] and far["family"] is None and far["nearest_family"] in (0, 1)


def test_features_are_the_encoders_pooled_statistics_and_the_code_histogram(tokenizer):
    images = torch.rand(5, 3, 32, 32, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        latents = tokenizer.autoencoder.encode(images * 2 - 1).double()
        codes = tokenizer.encode_codes(images)
    pooled = image_features(tokenizer, images, "pooled", batch_size=2)
    channels = latents.shape[1]
    assert pooled.shape == (5, 2 * channels) and pooled.dtype == torch.float64
    torch.testing.assert_close(pooled[:, :channels], latents.mean(dim=(2, 3)))
    torch.testing.assert_close(pooled[:, channels:], latents.std(dim=(2, 3), correction=0))
    histogram = image_features(tokenizer, images, "codes", batch_size=3)
    size = tokenizer.quantizer.codebook_size
    expected = torch.stack([torch.bincount(row.flatten(), minlength=size).double() / row.numel() for row in codes])
    torch.testing.assert_close(histogram, expected)
    torch.testing.assert_close(histogram.sum(dim=1), torch.ones(5, dtype=torch.float64))


def _variant(name, seed, **variant):
    return json.dumps({"name": name, "variant": {"seed": seed, **variant}})


def test_cluster_groups_variants_with_their_family_and_a_folder_joins_its_sensor(tokenizer_folder, tmp_path, capsys):
    from vqtouch.plugins.utils.images import save_png

    folder = tmp_path / "my_digit"
    folder.mkdir()
    digit = HOST.build(
        "dataset",
        {"name": "procedural", "num_samples": 8, "image_size": 32, "seed": 5},
        sensor=HOST.build("sensor_family", "digit"),
    )
    for index in range(8):
        save_png(digit[index]["tactile"], folder / f"frame_{index}.png")
    out = tmp_path / "families"
    gelsight_v1 = _variant("gelsight", 1, colour_gain=[1.05, 0.95, 0.95])
    sensors = ["gelsight", gelsight_v1, "digit", _variant("digit", 2, noise_std=0.02)]
    args = generator_runs.cluster_args(tokenizer_folder, out, [*sensors, str(folder)], image_size=32)
    args += ["--unseen", _variant("digit", 4)]
    assert main(args) == 0
    result = json.loads((out / "cluster.json").read_text())
    assigned = result["assignments"]["digit/v4"]
    assert assigned["family"] == result["sensor_family"]["digit"] and not assigned["refused"]
    assert assigned["threshold"] == result["refusal_threshold"] > 0
    assert (out / "families.png").is_file()
    family = result["sensor_family"]
    assert family["gelsight"] == family["gelsight/v1"] != family["digit"] == family["digit/v2"] == family["my_digit"]
    assert len(result["family_distances"]) == 2 and result["family_distances"][0][0] == 0.0
    assert [entry["images"] for entry in result["sensors"]] == [8] * 5
    assert "family 0: gelsight, gelsight/v1" in capsys.readouterr().out
    # Told to accept nothing, it refuses rather than assigning silently.
    assert main([*args, "--threshold", "0", "--overwrite"]) == 0
    assert json.loads((out / "cluster.json").read_text())["assignments"]["digit/v4"]["family"] is None
    assert "unseen digit/v4: refused: " in capsys.readouterr().out


@pytest.mark.parametrize(
    "sensors, message",
    [
        (["gelsight"], "--sensors: give at least two sensors to group into families"),
        (
            ["gelsight", "gelsite"],
            "sensor 'gelsite' is neither a folder nor a registered sensor family (digit, gelsight, gelsight_mini)",
        ),
        (["gelsight", "{bad json"], "sensor '{bad json': not a folder, a sensor name or valid JSON"),
    ],
)
def test_cluster_errors_are_one_line(tokenizer_folder, tmp_path, capsys, sensors, message):
    capsys.readouterr()
    assert (
        main(
            [
                "cluster",
                "--run",
                str(tokenizer_folder),
                "--image-size",
                "32",
                "--images",
                "4",
                "--out",
                str(tmp_path / "x"),
                "--sensors",
                *sensors,
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.startswith(f"vqtouch: error: {message}") and err.count("\n") == 1, err


@pytest.mark.parametrize(
    "option, value, message",
    [
        ("--keep", "0", "argument --keep: 0: must be a finite number in (0, 1]"),
        ("--refine-steps", "-1", "argument --refine-steps: -1: must be an integer >= 0"),
        ("--families", "-2", "argument --families: -2: must be an integer >= 0"),
    ],
)
def test_cluster_options_are_checked_in_one_line(tokenizer_folder, tmp_path, capsys, option, value, message):
    capsys.readouterr()
    argv = ["cluster", "--run", str(tokenizer_folder), "--out", str(tmp_path / "x"), "--sensors", "gelsight", "digit"]
    assert main([*argv, f"{option}={value}"]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err


def test_cluster_refuses_an_empty_folder_and_names_a_corrupt_file(tokenizer_folder, tmp_path, capsys):
    empty, corrupt = tmp_path / "empty", tmp_path / "corrupt"
    empty.mkdir()
    corrupt.mkdir()
    (corrupt / "broken.png").write_bytes(b"not a png")
    for folder, message in ((empty, "no image files (png, jpg, ...) in this folder"), (corrupt, "cannot decode image")):
        capsys.readouterr()
        assert (
            main(
                [
                    "cluster",
                    "--run",
                    str(tokenizer_folder),
                    "--image-size",
                    "32",
                    "--images",
                    "4",
                    "--out",
                    str(tmp_path / "x"),
                    "--sensors",
                    "gelsight",
                    str(folder),
                ]
            )
            == 2
        )
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, err


def test_features_and_families_do_not_depend_on_the_thread_count():
    """Parallel sums add in a thread-count-dependent order (the bundled tokenizer's features differ by
    ~3e-8 between 1 and 2 threads, enough to flip a family count chosen by silhouette); features,
    prototypes, families and assignments are computed on one thread, and the caller's thread count
    is left as it was.  The bundled tokenizer at 64 px: a tiny one's tensors are too small to be
    split between threads at all."""
    from vqtouch.plugins.adaptation.families import cluster_prototypes
    from vqtouch.plugins.pretrained.bundle import load_bundle

    tokenizer = load_bundle("tour", HOST, tokenizer_only=True).tokenizer
    # 40 images: encoded as batches of 32 and 8, and the batch of 8 is where the threads split sums.
    images = torch.rand(40, 3, 64, 64, generator=torch.Generator().manual_seed(3))
    before = torch.get_num_threads()
    results = []
    try:
        for threads in (1, 2, 1, 2):
            torch.set_num_threads(threads)
            features = image_features(tokenizer, images)
            assert torch.get_num_threads() == threads
            prototypes = torch.stack([sensor_prototype(part) for part in features.split(8)])
            clusterer = HOST.build("clusterer", {"name": "kmeans", "num_families": 0, "max_families": 4})
            families = cluster_prototypes([f"s{i}" for i in range(5)], prototypes, clusterer)
            results.append((features, prototypes, json.dumps(families, sort_keys=True)))
    finally:
        torch.set_num_threads(before)
    for features, prototypes, families in results[1:]:
        assert torch.equal(features, results[0][0]) and torch.equal(prototypes, results[0][1])
        assert families == results[0][2]


def test_the_families_picture_keys_sensors_by_number_and_no_two_labels_overlap():
    """Variants of one sensor sit on top of each other in the PCA picture: their labels must not."""
    from types import SimpleNamespace

    from vqtouch.plugins.adaptation.families import families_figure

    generator = torch.Generator().manual_seed(0)
    centres = torch.tensor([[0.0, 0.0], [0.0, 0.0], [0.01, 0.0], [5.0, 5.0], [5.0, 5.01]])
    features = [centre + 0.01 * torch.randn(6, 2, generator=generator) for centre in centres]
    prototypes = torch.stack([part.mean(dim=0) for part in features])
    names = ["gelsight", "gelsight/v1", "gelsight/v2", "digit", "digit/v1"]
    unseen = SimpleNamespace(name="mine", verdict="family 0", features=features[0], prototype=prototypes[0])
    figure = families_figure(names, features, prototypes, [0, 0, 0, 1, 1], "t", [unseen])
    axes = figure.axes[0]
    renderer = figure.canvas.get_renderer()
    boxes = [text.get_window_extent(renderer) for text in axes.texts]
    assert [text.get_text() for text in axes.texts] == ["1", "2", "3", "4", "5", "mine (unseen: family 0)"]
    assert not any(a.overlaps(b) for i, a in enumerate(boxes) for b in boxes[i + 1 :])
    legend = [text.get_text() for text in axes.get_legend().get_texts()]
    assert legend == ["family 0: 1 gelsight, 2 gelsight/v1, 3 gelsight/v2", "family 1: 4 digit, 5 digit/v1"]


def test_a_sensor_folder_may_be_a_data_render_export_or_class_sub_folders(tmp_path):
    """`cluster` and `adapt` read any folder the image_folder reader takes: the images directly in it,
    an export of `vqtouch data render` (index.csv; not its visual images or preview), or one
    sub-folder per class; a folder with none of them is one line naming the layouts."""
    from vqtouch.core import DatasetError
    from vqtouch.plugins.utils.images import ImageLoader, save_png
    from vqtouch.plugins.adaptation.families import sensor_images
    from vqtouch.plugins.data.sensor_folders import sensor_folder_files

    export = tmp_path / "export"
    args = ["--no-progress", "data", "render", "--sensor", "digit", "--n", "6", "--image-size", "32"]
    assert main([*args, "--out", str(export)]) == 0
    index = (export / "index.csv").read_text().splitlines()
    column = index[0].split(",").index("path")
    expected = [export / row.split(",")[column] for row in index[1:]]
    assert sensor_folder_files(export, HOST) == expected and all("tactile" in path.parts for path in expected)
    loaded = sensor_images(str(export), HOST, count=100, image_size=32).images
    loader = ImageLoader(size=32)
    assert torch.equal(loaded, torch.stack([loader.load(path) for path in expected]))

    classes = tmp_path / "classes"
    for name, images in (("sphere", 2), ("edge", 3)):
        (classes / name / "rec1").mkdir(parents=True)
        for index in range(images):
            save_png(torch.rand(3, 32, 32), classes / name / "rec1" / f"{index}.png")
    files = sensor_folder_files(classes, HOST)
    assert [path.relative_to(classes).as_posix() for path in files] == [
        "edge/rec1/0.png",
        "edge/rec1/1.png",
        "edge/rec1/2.png",
        "sphere/rec1/0.png",
        "sphere/rec1/1.png",
    ]
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="no image files .* no index.csv and no class sub-folders"):
        sensor_folder_files(tmp_path / "empty", HOST)

"""Sensor-family clusterers: families recovered from well-separated
prototypes, the family count chosen by silhouette, nearest-family-mean assignment, fitted state
through a checkpoint, and one-line errors."""

import pytest
import torch

from vqtouch.core import ConfigError, load, load_plugins, save

HOST = load_plugins(autoload=False)
CLUSTERERS = ["kmeans", "agglomerative"]


def families(seed=0, per_family=4, centres=((0.0, 0.0, 0.0), (10.0, 0.0, 0.0), (0.0, 10.0, 5.0))):
    """Per-sensor prototypes: ``per_family`` variants (small spread) around each family centre, and
    the true family of each row."""
    generator = torch.Generator().manual_seed(seed)
    rows, truth = [], []
    for family, centre in enumerate(centres):
        rows.append(torch.tensor(centre) + 0.3 * torch.randn(per_family, len(centre), generator=generator))
        truth += [family] * per_family
    return torch.cat(rows), torch.tensor(truth)


@pytest.mark.parametrize("name", CLUSTERERS)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_families_are_recovered_and_their_count_chosen_by_silhouette(name, seed):
    from sklearn.metrics import adjusted_rand_score

    features, truth = families(seed)
    clusterer = HOST.build("clusterer", name)  # num_families=0: chosen by silhouette
    labels = clusterer.fit(features)
    assert clusterer.num_families == 3
    assert adjusted_rand_score(truth.numpy(), labels.numpy()) == 1.0
    assert labels[0] == 0  # numbered by first appearance
    # The kept centroids are the family means of the members (computed here independently).
    for family in range(3):
        torch.testing.assert_close(clusterer.centroids_KF[family], features[labels == family].double().mean(dim=0))


@pytest.mark.parametrize("name", CLUSTERERS)
def test_an_unseen_sensor_joins_the_nearest_family_mean(name):
    features, truth = families(0)
    clusterer = HOST.build("clusterer", {"name": name, "num_families": 3})
    labels = clusterer.fit(features)
    held_out, held_truth = families(7, per_family=2)
    predicted = clusterer.predict(held_out)
    family_of_true = {int(t): int(label) for t, label in zip(truth, labels)}
    assert [family_of_true[int(t)] for t in held_truth] == predicted.tolist()
    distances = clusterer.distances(held_out)
    means = torch.stack([features[labels == f].double().mean(0) for f in range(3)])
    torch.testing.assert_close(distances, torch.cdist(held_out.double(), means))


@pytest.mark.parametrize("name", CLUSTERERS)
def test_a_fitted_clusterer_survives_its_checkpoint(name, tmp_path):
    features, _ = families(0)
    clusterer = HOST.build("clusterer", name)
    clusterer.fit(features)
    path = save(clusterer, tmp_path / "clusterer.safetensors", host=HOST)
    restored = load(path, host=HOST)
    assert restored.num_families == 3
    probe, _ = families(5)
    assert torch.equal(restored.predict(probe), clusterer.predict(probe))


@pytest.mark.parametrize("name", CLUSTERERS)
def test_degenerate_sets_and_bad_input(name):
    clusterer = HOST.build("clusterer", name)
    # One sensor, or identical prototypes: one family, nothing to compare.
    assert clusterer.fit(torch.ones(1, 4)).tolist() == [0] and clusterer.num_families == 1
    assert clusterer.fit(torch.zeros(5, 4)).tolist() == [0] * 5 and clusterer.num_families == 1
    with pytest.raises(
        ConfigError,
        match=r"^3 families asked of 2 distinct sensor feature\(s\); set num_families "
        r"<= 2, or 0 to choose by silhouette$",
    ):
        HOST.build("clusterer", {"name": name, "num_families": 3}).fit(torch.tensor([[0.0], [1.0], [1.0]]))
    with pytest.raises(ValueError, match="features contain NaN or Inf"):
        clusterer.fit(torch.tensor([[0.0, float("nan")], [1.0, 1.0]]))
    with pytest.raises(RuntimeError, match=r"not fitted: call fit\(\) first"):
        HOST.build("clusterer", name).predict(torch.zeros(2, 4))
    with pytest.raises(ValueError, match="features have 2 dimensions; the families were fitted on 4"):
        clusterer.predict(torch.zeros(1, 2))


def test_a_family_count_silhouette_cannot_settle_is_said_with_the_fix():
    """Three distinct sensors alone: silhouette can score 2 families, never 3, so it merges two
    designs; close silhouettes are uncertain too; a clear count and a given one carry no note."""
    from vqtouch.plugins.adaptation.families import cluster_prototypes

    three = torch.tensor([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]], dtype=torch.float64)
    clusterer = HOST.build("clusterer", {"name": "kmeans", "num_families": 0, "max_families": 6})
    result = cluster_prototypes(["gelsight", "gelsight_mini", "digit"], three, clusterer)
    assert len(result["families"]) == 2 and result["family_count"]["silhouette"] == {2: pytest.approx(0.0976, abs=1e-3)}
    note = result["family_count"]["uncertain"]
    assert note.startswith("family count uncertain: with 3 distinct sensors the silhouette can compare 2 to 2")
    assert "pass --families K" in note

    generator = torch.Generator().manual_seed(0)
    centres = torch.tensor([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]], dtype=torch.float64)
    variants = torch.cat(
        [centre + 0.1 * torch.randn(4, 2, generator=generator, dtype=torch.float64) for centre in centres]
    )
    names = [f"s{i}" for i in range(len(variants))]
    clear = cluster_prototypes(names, variants, HOST.build("clusterer", {"name": "kmeans", "num_families": 0}))
    assert len(clear["families"]) == 3 and "uncertain" not in clear["family_count"]

    # Three pairs, two of them 2.0 apart: 2 families score 0.857, 3 families 0.810.
    close = torch.tensor([[0, 0], [0, 0.5], [0, 2.0], [0, 2.5], [8, 0], [8, 0.5]], dtype=torch.float64)
    kmeans = HOST.build("clusterer", {"name": "kmeans", "num_families": 0})
    result = cluster_prototypes([f"c{i}" for i in range(6)], close, kmeans)
    assert len(result["families"]) == 2
    assert result["family_count"]["uncertain"] == (
        "family count uncertain: silhouette 0.857 for 2 families, 0.810 for 3 (within 0.05); "
        "pass --families K (cluster.clusterer.num_families in a scene) to set the count"
    )

    given = cluster_prototypes(["a", "b", "c"], three, HOST.build("clusterer", {"name": "kmeans", "num_families": 3}))
    assert given["family_count"] == {"chosen_by": "given"}

"""Distribution scores of generated images (vqtouch.plugins.evaluation.distribution): fd_effnetlite0
against the real held-out images and a classifier trained on real images, on hand-built sets."""

import pytest
import torch

from vqtouch.plugins.evaluation.distribution import DistributionScorer
from vqtouch.plugins.evaluation.fd_metric import feature_frechet_distance
from vqtouch.plugins.evaluation.fd_metric import FdEffNetLite0, FeatureMoments, frechet_distance

#: 32 px features: the smallest EfficientNet-Lite0 input, fast on a CPU.
SIZE = 32


def two_classes(per_class: int, seed: int) -> tuple[torch.Tensor, list[int]]:
    """A trivially separable set: class 0 dark and flat, class 1 bright with horizontal stripes
    (each image with its own faint noise); class 0 first."""
    generator = torch.Generator().manual_seed(seed)
    dark = 0.2 + 0.05 * torch.rand(per_class, 3, SIZE, SIZE, generator=generator)
    bright = 0.8 + 0.05 * torch.rand(per_class, 3, SIZE, SIZE, generator=generator)
    bright[..., ::4, :] = 0.1
    return torch.cat([dark, bright]).clamp(0, 1), [0] * per_class + [1] * per_class


@pytest.fixture(scope="module")
def metric():
    return FdEffNetLite0(image_size=SIZE)


@pytest.fixture(scope="module")
def separable(metric):
    train, train_labels = two_classes(6, seed=1)
    held_out, labels = two_classes(4, seed=2)
    return DistributionScorer(held_out, labels, train, train_labels, metric=metric, seed=0), held_out, labels


def test_a_classifier_trained_on_real_images_is_right_on_real_images_and_exactly_at_chance_on_a_constant(separable):
    scorer, held_out, labels = separable
    assert scorer.real_scores() == {"real_classifier_accuracy": 1.0, "classifier_train_images": 12}
    assert scorer.score(held_out)["classifier_accuracy"] == 1.0
    # Each condition given the other class's image: every one is wrong.
    assert scorer.score(torch.cat([held_out[4:], held_out[:4]]))["classifier_accuracy"] == 0.0
    # One image for every condition: one predicted class, right for exactly the 4 of 8 conditions of
    # that class (the held-out set is balanced).
    assert scorer.score(torch.full_like(held_out, 0.5))["classifier_accuracy"] == 0.5


def test_fd_effnetlite0_of_a_set_with_itself_is_zero(separable):
    scorer, held_out, _ = separable
    assert abs(scorer.score(held_out)["fd_effnetlite0"]) < 1e-3
    noise = torch.rand(held_out.shape, generator=torch.Generator().manual_seed(3))
    assert scorer.score(noise)["fd_effnetlite0"] > 1
    features = scorer.features(held_out)
    assert feature_frechet_distance(features, features) == pytest.approx(0, abs=1e-6)


@pytest.mark.parametrize("width, rows", [(16, 6), (16, 40), (1280, 12)])
def test_fd_effnetlite0_is_the_metrics_frechet_distance(width, rows):
    """Fewer rows than features: computed in the rows' space; the metric's maths give the same number
    (up to the round-off of their eigenvalues of a rank-deficient matrix, clamped at 0)."""
    generator = torch.Generator().manual_seed(width + rows)
    first = torch.randn(rows, width, generator=generator, dtype=torch.float64)
    second = 0.5 + 2 * torch.randn(rows + 3, width, generator=generator, dtype=torch.float64)
    moments = []
    for features in (first, second):
        accumulated = FeatureMoments()
        accumulated.add(features)
        moments.append(accumulated.mean_and_covariance())
    expected = frechet_distance(*moments[0], *moments[1])
    assert feature_frechet_distance(first, second) == pytest.approx(expected, rel=1e-6)


def test_the_fd_metric_streams_batches_to_the_same_number(monkeypatch):
    """The fd_effnetlite0 metric fed in batches, below and above the feature width, gives the distance
    of all its rows at once (stand-in features: the network is not what is tested)."""
    from vqtouch.plugins.evaluation import fd_metric

    generator = torch.Generator().manual_seed(3)
    for rows, width in ((10, 16), (40, 16)):
        monkeypatch.setattr(fd_metric, "EFFNET_LITE0_POOLED_DIM", width)
        metric = fd_metric.FdEffNetLite0.__new__(fd_metric.FdEffNetLite0)
        metric.reset()
        predicted = torch.randn(rows, width, generator=generator, dtype=torch.float64)
        target = 1 + torch.randn(rows, width, generator=generator, dtype=torch.float64)
        features = {}
        monkeypatch.setattr(metric, "pooled_features", lambda images: features[id(images)], raising=False)
        for start in range(0, rows, 4):
            a, b = torch.zeros(1), torch.zeros(1)
            features[id(a)], features[id(b)] = predicted[start : start + 4], target[start : start + 4]
            metric.update(a, b)
        moments = []
        for rows_NF in (predicted, target):
            accumulated = FeatureMoments()
            accumulated.add(rows_NF)
            moments.append(accumulated.mean_and_covariance())
        assert metric.compute() == pytest.approx(frechet_distance(*moments[0], *moments[1]), rel=1e-6)
        assert bool(metric._predicted_rows) == (rows < width)


def test_a_constant_set_is_featurised_once_and_like_any_other_set(separable):
    scorer, _, _ = separable
    # One textured image eight times (a uniform one has all-zero features at 32 px).
    constant = torch.rand(1, 3, SIZE, SIZE, generator=torch.Generator().manual_seed(4)).expand(8, -1, -1, -1)
    assert float(scorer.metric.pooled_features(constant[:1]).abs().sum()) > 0
    torch.testing.assert_close(scorer.features(constant), scorer.metric.pooled_features(constant), rtol=0, atol=1e-5)


def test_the_scores_are_deterministic(separable, metric):
    _, held_out, labels = separable
    train, train_labels = two_classes(6, seed=1)
    noisy = (held_out + 0.2 * torch.rand(held_out.shape, generator=torch.Generator().manual_seed(5))).clamp(0, 1)
    first, second = (
        DistributionScorer(held_out, labels, train, train_labels, metric=metric, seed=0).score(noisy) for _ in range(2)
    )
    assert first == second


@pytest.mark.parametrize(
    "labels, train_labels, reason",
    [
        (None, [0] * 6 + [1] * 6, "the dataset has no labels"),
        ([0] * 4 + [1] * 4, None, "the dataset has no labels"),
        ([0] * 8, [3] * 12, "the training images have only one class ([3]); a classifier needs two"),
    ],
)
def test_the_classifier_is_skipped_with_a_reason(metric, labels, train_labels, reason):
    held_out, _ = two_classes(4, seed=2)
    train, _ = two_classes(6, seed=1)
    scorer = DistributionScorer(held_out, labels, train, train_labels, metric=metric)
    assert scorer.real_scores() == {"classifier_skipped": reason}
    assert set(scorer.score(held_out)) == {"fd_effnetlite0"}


def test_one_image_per_condition_is_required(separable):
    scorer, held_out, _ = separable
    with pytest.raises(ValueError, match="7 images for 8 held-out conditions"):
        scorer.score(held_out[:7])

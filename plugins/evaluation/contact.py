"""Where a tactile image shows a contact: the pixels that differ from the sensor's no-contact image.

Tactile images are mostly static background, so scores and checks that matter look at the
contact region.  A pixel is in it when its mean absolute difference from the background over the
RGB channels exceeds both a fixed floor and what the camera's noise alone would produce: the noise
level is estimated from the differences themselves (1.4826 x their median absolute value, the
normal-consistent median absolute deviation: most pixels of a tactile image are background, so
the median sees noise, not contact), and the mean absolute value of three channels of pure
Gaussian noise exceeds :data:`NOISE_FACTOR` sigma on about 6e-5 of the pixels.  Noise-free
renders (GelSight) keep the floor exactly; DIGIT's published 7/255 camera noise raises the bar
instead of turning every pixel into "contact".

The background of a dataset (:func:`dataset_background`, what every stage scores against) is the
no-contact render of its rendering sensor when the dataset renders its images (the procedural
scenes), and for captured frames, which hold no no-contact frame, the per-pixel median of up to
:data:`MAX_BACKGROUND_IMAGES` of them (contacts move around, the background stays).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch

#: A pixel is in contact where it differs from the background by more than this (mean absolute
#: difference over the channels, images in [0, 1]), when the noise allows no less.
CONTACT_THRESHOLD = 0.02
#: ... and by more than this many standard deviations of the estimated noise.
NOISE_FACTOR = 2.5
#: The background of captured frames is the per-pixel median of at most this many of them.
MAX_BACKGROUND_IMAGES = 256
#: How :func:`dataset_background` says it made a rendering sensor's background.
RENDERED_BACKGROUND = "the sensor's rendering of no contact"


def contact_mask(
    images_B3HW: torch.Tensor, background_B3HW: torch.Tensor, threshold: float = CONTACT_THRESHOLD
) -> torch.Tensor:
    """(B, H, W) bool: the pixels of ``images_B3HW`` in contact, given the no-contact image(s)
    ``background_B3HW`` (broadcast against the images; see the module docstring)."""
    difference = images_B3HW.detach().float().cpu() - background_B3HW.detach().float().cpu()
    noise_sigma = 1.4826 * float(difference.abs().median())
    return difference.abs().mean(dim=1) > max(threshold, NOISE_FACTOR * noise_sigma)


def no_contact_image(sensor: Any, truth_B3HW: torch.Tensor) -> torch.Tensor | None:
    """``sensor`` rendering no contact, one copy per ground-truth image: what a model that ignores
    its input and draws only the background would score.  None without a sensor."""
    if sensor is None:
        return None
    flat = sensor.render(torch.zeros(1, *truth_B3HW.shape[-2:]), generator=torch.Generator().manual_seed(0))
    return flat.to(truth_B3HW).expand_as(truth_B3HW)


def evenly_spaced(count: int, max_images: int = MAX_BACKGROUND_IMAGES) -> list[int]:
    """At most ``max_images`` of the indices ``0 .. count - 1``, evenly spaced from the first to the
    last: the images a median background is estimated from (neighbouring frames of a recording
    share their contact, so a spread draw sees the contacts in different places)."""
    chosen = min(count, max_images)
    return [round(i * (count - 1) / max(1, chosen - 1)) for i in range(chosen)]


def median_background(images_N3HW: torch.Tensor) -> torch.Tensor:
    """(3, H, W): the per-pixel median of the images, the no-contact background of captured frames
    (contacts move around, the background stays: a pixel in contact in fewer than half of the
    images keeps its background value)."""
    return images_N3HW.detach().float().median(dim=0).values


def dataset_background(
    dataset: Any, image_hw: tuple[int, int], max_images: int = MAX_BACKGROUND_IMAGES, images_are: str = "training"
) -> tuple[torch.Tensor | None, str]:
    """The (3, H, W) no-contact image of ``dataset``'s tactile images and how it was made: the
    no-contact render of the dataset's rendering sensor (``dataset.rendering_sensor()``, exact) when
    it renders its images, else the per-pixel median (:func:`median_background`) of at most
    ``max_images`` evenly spaced samples' ``"tactile"`` images.  None, with the reason, for
    captured frames fewer than 2.  Every stage's background comes from here; callers pass the
    training split, never the held-out images being scored; ``images_are`` says what the images
    are in the description (``training``; ``evaluated`` for a dataset scored whole)."""
    sensor = dataset.rendering_sensor()
    if sensor is not None:
        return no_contact_image(sensor, torch.zeros(1, 3, *image_hw))[0], RENDERED_BACKGROUND
    if len(dataset) < 2:
        return None, (
            f"none: the dataset's {len(dataset)} captured image(s) are too few for a per-pixel median "
            "background (it needs at least 2)"
        )
    indices = evenly_spaced(len(dataset), max_images)
    images = torch.stack([dataset[index]["tactile"] for index in indices])
    if tuple(images.shape[-2:]) != tuple(image_hw):
        raise ValueError(
            f"the dataset's images are {tuple(images.shape[-2:])} pixels, not the {tuple(image_hw)} asked for"
        )
    return median_background(images), (
        f"the per-pixel median of {len(indices)} of {len(dataset)} {images_are} images "
        "(captured frames hold no no-contact frame)"
    )


class ContactRegionScores:
    """Scores on the contact region only, accumulated over batches: pixels where the ground truth
    differs from the no-contact image by more than the threshold and the camera noise allow
    (:func:`contact_mask`, the noise estimated per batch).  Whole-image scores flatter a model that
    draws only the background; these do not.

    ``update({prefix: images}, truth)`` adds candidates (``{"": reconstructed, "background_": ...}``);
    :meth:`scores` gives ``{prefix}contact_psnr`` (torchmetrics' PSNR of the error pooled over the
    region's pixels, capped at 100 dB), ``{prefix}contact_mae``, ``{prefix}contact_ssim`` (the SSIM
    map of the ``ssim`` metric's default window averaged over the region's pixels and channels; only
    for images at least that window wide) and ``contact_fraction``, the region's share of the pixels
    (0 and no other score when no pixel is in contact).
    """

    def __init__(self, background_B3HW: torch.Tensor, max_db: float = 100.0) -> None:
        self.background = background_B3HW.detach().float().cpu()
        self.max_db = max_db
        self.region_pixels, self.pixels = 0, 0
        self._psnr: dict[str, Any] = {}
        self._absolute: dict[str, tuple[float, int]] = {}
        self._ssim: dict[str, tuple[float, int]] = {}
        # Per image: the region's squared error per candidate and its value count, for the bootstrap
        # of the gaps (:func:`psnr_gap_interval`); and per-pixel sums across images for the spread.
        self._squared_errors: dict[str, list[float]] = {}
        self._region_values: list[int] = []
        self._moments: dict[str, tuple[torch.Tensor, torch.Tensor, int]] = {}
        self._cross: Any = 0.0  # per pixel: the sum over images of the model's value times the truth's

    def update(self, candidates: Mapping[str, torch.Tensor], truth_B3HW: torch.Tensor) -> None:
        """Add one batch: each candidate image set against its ground truth (image i against truth i)."""
        from torchmetrics.image import PeakSignalNoiseRatio

        truth = truth_B3HW.detach().float().cpu()
        background = self.background[: len(truth)] if len(self.background) > 1 else self.background
        region_BHW = contact_mask(truth, background)
        self.region_pixels += int(region_BHW.sum())
        self.pixels += region_BHW.numel()
        mask = region_BHW.unsqueeze(1).expand_as(truth)
        self._region_values += [int(count) for count in mask.flatten(1).sum(dim=1)]
        if "" in candidates:  # the spread and correlation are the model's only
            model = candidates[""].detach().float().cpu()
            self._add_moments(TRUTH_KEY, truth)
            self._add_moments("", model)
            self._cross = self._cross + (model.double() * truth.double()).sum(dim=0)
        for prefix, predicted in candidates.items():
            predicted = predicted.detach().float().cpu()
            squared = ((predicted.double() - truth.double()) ** 2) * mask
            self._squared_errors.setdefault(prefix, []).extend(squared.flatten(1).sum(dim=1).tolist())
            predicted_region = predicted[mask].double()
            psnr = self._psnr.setdefault(prefix, PeakSignalNoiseRatio(data_range=1.0).double())
            total, count = self._absolute.get(prefix, (0.0, 0))
            if predicted_region.numel():
                psnr.update(predicted_region, truth[mask].double())
                total += float((predicted_region - truth[mask].double()).abs().sum())
                count += predicted_region.numel()
                ssim_map = _ssim_map(predicted, truth)
                if ssim_map is not None:
                    ssim_total, ssim_count = self._ssim.get(prefix, (0.0, 0))
                    self._ssim[prefix] = (ssim_total + float(ssim_map[mask].sum()), ssim_count + int(mask.sum()))
            self._absolute[prefix] = (total, count)

    def _add_moments(self, key: str, images_B3HW: torch.Tensor) -> None:
        images = images_B3HW.double()
        total, squares, count = self._moments.get(key, (0.0, 0.0, 0))
        self._moments[key] = (total + images.sum(dim=0), squares + (images**2).sum(dim=0), count + len(images))

    def _spread(self, key: str) -> float:
        """The mean over pixels of the standard deviation across images of ``key``'s images."""
        total, squares, count = self._moments[key]
        mean = total / count
        return float((squares / count - mean**2).clamp_min(0).sqrt().mean())

    def _input_correlation(self) -> float:
        """The correlation between the model's and the truths' deviations from their per-pixel means
        across images, pooled over pixels: 0 for a constant output (or one unrelated to the input)."""
        total_o, squares_o, count = self._moments[""]
        total_t, squares_t, _ = self._moments[TRUTH_KEY]
        mean_o, mean_t = total_o / count, total_t / count
        covariance = float((self._cross / count - mean_o * mean_t).sum())
        variance_o = float((squares_o / count - mean_o**2).clamp_min(0).sum())
        variance_t = float((squares_t / count - mean_t**2).clamp_min(0).sum())
        if variance_o <= 1e-12 or variance_t <= 1e-12:
            return 0.0
        return covariance / (variance_o * variance_t) ** 0.5

    def scores(self) -> dict[str, float]:
        """The region's share of the pixels, each candidate's contact PSNR and MAE, the 95% bootstrap
        interval of the model's contact PSNR gap to each other candidate and the model's output spread
        (see :data:`OUTPUT_SPREAD_KEY`)."""
        scores: dict[str, float] = {}
        if "" in self._moments and self._moments[TRUTH_KEY][2] > 1:
            truth_spread = self._spread(TRUTH_KEY)
            if truth_spread > 0:
                scores[OUTPUT_SPREAD_KEY] = round(self._spread("") / truth_spread, 4)
                scores[INPUT_CORRELATION_KEY] = round(self._input_correlation(), 4)
        if self.region_pixels == 0:
            return {"contact_fraction": 0.0, **scores}
        scores = {"contact_fraction": round(self.region_pixels / self.pixels, 4), **scores}
        if "" in self._squared_errors:
            for prefix in self._squared_errors:
                if prefix:
                    low, high = psnr_gap_interval(
                        self._squared_errors[""], self._squared_errors[prefix], self._region_values, self.max_db
                    )
                    scores[gap_interval_key(prefix, "low")] = round(low, 4)
                    scores[gap_interval_key(prefix, "high")] = round(high, 4)
        for prefix, psnr in self._psnr.items():
            total, count = self._absolute[prefix]
            scores[f"{prefix}contact_psnr"] = round(min(float(psnr.compute()), self.max_db), 4)
            scores[f"{prefix}contact_mae"] = round(total / count, 5)
            if prefix in self._ssim:
                ssim_total, ssim_count = self._ssim[prefix]
                scores[f"{prefix}contact_ssim"] = round(ssim_total / ssim_count, 4)
        return scores


def _ssim_map(predicted_B3HW: torch.Tensor, truth_B3HW: torch.Tensor) -> torch.Tensor | None:
    """The per-pixel SSIM map (B, 3, H, W), float64, with the ``ssim`` metric's default window (its
    whole-image score is this map's mean); None for images narrower than the window."""
    from torchmetrics.functional.image import structural_similarity_index_measure

    from .metrics import SsimConfig

    window = SsimConfig()
    if min(truth_B3HW.shape[-2:]) < window.window_size:
        return None
    _, ssim_map = structural_similarity_index_measure(
        predicted_B3HW.double(),
        truth_B3HW.double(),
        data_range=window.data_range,
        kernel_size=window.window_size,
        sigma=window.sigma,
        reduction="none",
        return_full_image=True,
    )
    return ssim_map


#: ``scores()``' key of the model's (the ``""`` candidate's) output spread: the standard deviation
#: of its images across inputs, averaged over pixels, as a share of the ground truths' own.  Near 0,
#: the model draws nearly the same image whatever its input (a constant image scores 0).
OUTPUT_SPREAD_KEY = "output_spread_ratio"
#: ... and the correlation of its images' deviations from their per-pixel mean across inputs with
#: the ground truths' (1: they vary as the truths do; about 0: constant, or unrelated to the input,
#: such as the same blob in a different colour each time).
INPUT_CORRELATION_KEY = "input_correlation"
TRUTH_KEY = "\0truth"
#: Bootstrap resamples of the held-out images behind the gap intervals (seeded: the same scores
#: give the same interval).
BOOTSTRAP_RESAMPLES = 1000


def gap_interval_key(prefix: str, end: str) -> str:
    """The key of the ``end`` (``low`` or ``high``) of the 95% interval of the model's contact PSNR
    minus candidate ``prefix``'s (``background_`` -> ``contact_psnr_gap_low95_vs_background``)."""
    return f"contact_psnr_gap_{end}95_vs_{prefix.rstrip('_')}"


#: The comparisons a verdict weighs the model against (what drawing without the model gets).
VERDICT_BASELINE_PREFIXES = ("background_", "retrieval_", "class_mean_")
#: The scores a report's verdict weighs besides the contact scores themselves: a stage that lists
#: what its report shows lists these too.
VERDICT_EVIDENCE = (
    OUTPUT_SPREAD_KEY,
    INPUT_CORRELATION_KEY,
    *(gap_interval_key(prefix, end) for prefix in VERDICT_BASELINE_PREFIXES for end in ("low", "high")),
)


def psnr_gap_interval(
    model_errors: list[float], rival_errors: list[float], values: list[int], max_db: float = 100.0
) -> tuple[float, float]:
    """The 95% percentile-bootstrap interval over images of pooled PSNR(model) - PSNR(rival) in dB,
    from each image's summed squared error on the region and its count of values there: how far the
    gap could move with another draw of held-out images of the same kind."""
    model = torch.tensor(model_errors, dtype=torch.float64)
    rival = torch.tensor(rival_errors, dtype=torch.float64)
    counts = torch.tensor(values, dtype=torch.float64)
    generator = torch.Generator().manual_seed(0)
    draws_RN = torch.randint(len(counts), (BOOTSTRAP_RESAMPLES, len(counts)), generator=generator)
    total = counts[draws_RN].sum(dim=1).clamp_min(1)

    def psnr(errors: torch.Tensor) -> torch.Tensor:
        mse = errors[draws_RN].sum(dim=1) / total
        return (-10 * torch.log10(mse.clamp_min(1e-300))).clamp(max=max_db)

    gaps = psnr(model) - psnr(rival)
    return float(gaps.quantile(0.025)), float(gaps.quantile(0.975))


def contact_region_scores(
    candidates: Mapping[str, torch.Tensor], truth_B3HW: torch.Tensor, background_B3HW: torch.Tensor
) -> dict[str, float]:
    """:class:`ContactRegionScores` of one batch of candidates."""
    accumulated = ContactRegionScores(background_B3HW)
    accumulated.update(candidates, truth_B3HW)
    return accumulated.scores()


def contact_centroids(images_B3HW: torch.Tensor, background_B3HW: torch.Tensor) -> torch.Tensor:
    """(B, 2) the (row, column) centre of each image's contact region (:func:`contact_mask`), each
    pixel weighted by how far it is from the no-contact image; the image centre for an image with
    no contact pixel (what a guess without the condition would say)."""
    difference_BHW = (images_B3HW.detach().float().cpu() - background_B3HW.detach().float().cpu()).abs().mean(dim=1)
    weight_BHW = difference_BHW * contact_mask(images_B3HW, background_B3HW)
    height, width = weight_BHW.shape[-2:]
    rows = torch.arange(height, dtype=torch.float32).view(1, -1, 1)
    cols = torch.arange(width, dtype=torch.float32).view(1, 1, -1)
    total_B = weight_BHW.sum(dim=(1, 2))
    centre = torch.tensor([(height - 1) / 2, (width - 1) / 2])
    found_B = total_B > 0
    safe_B = total_B.clamp_min(1e-12)
    centres_B2 = torch.stack([(weight_BHW * rows).sum((1, 2)) / safe_B, (weight_BHW * cols).sum((1, 2)) / safe_B], 1)
    return torch.where(found_B[:, None], centres_B2, centre.expand_as(centres_B2))


def contact_centroid_errors(
    candidates: Mapping[str, torch.Tensor], truth_B3HW: torch.Tensor, background_B3HW: torch.Tensor
) -> dict[str, float]:
    """``{prefix}contact_centroid_error_px``: the mean distance in pixels between the contact centre
    (:func:`contact_centroids`) of each candidate image and of its ground truth (the no-contact
    image's own is the error of always guessing the image centre)."""
    truth_B2 = contact_centroids(truth_B3HW, background_B3HW)
    return {
        f"{prefix}contact_centroid_error_px": float(
            (contact_centroids(images, background_B3HW) - truth_B2).norm(dim=1).mean()
        )
        for prefix, images in candidates.items()
    }

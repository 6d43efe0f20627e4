"""Training and evaluating a tactile tokenizer (any autoencoder plugin + any quantizer plugin).

Objective (VQGAN's, with its safeguards)::

    nll   = l1_weight * |x - x_hat| + perceptual_weight * P(x_hat, x)
    g     = -mean D(x_hat)                                   (from disc_start on)
    L_G   = nll + lambda * adversarial_weight * g + codebook_weight * L_vq
    L_D   = 0.5 * (mean relu(1 - D(x)) + mean relu(1 + D(x_hat)))   (hinge)

``lambda`` is the adaptive weight at the decoder's last layer (fp32, clamped, 0 when not
finite).  The discriminator is not trained before ``disc_start``.  Images enter in [-1, 1].
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from vqtouch.core import Autoencoder, Metric, Quantizer, VqtouchError
from vqtouch.plugins.evaluation.metric_set import MetricSet
from vqtouch.core.errors import NothingToEvaluateError
from vqtouch.plugins.training.batches import collate_samples

from .discriminator import adaptive_weight, hinge_discriminator_loss
from .quantizers import perplexity_of_counts
from .stages_plugin import TokenizerLossConfig, TokenizerSection, disc_start_step
from .stages_plugin import TokenizerTrainConfig  # noqa: F401 - re-exported: its old home
from vqtouch.plugins.evaluation.contact import ContactRegionScores


def adversarial_never_trains(section: TokenizerSection) -> str | None:
    """Why the configured adversarial term would never train in this run, or None when it does (or is off)."""
    loss, steps = section.loss, section.train.steps
    if section.discriminator is None or loss.adversarial_weight == 0 or steps == 0:
        return None
    start = disc_start_step(loss.disc_start, steps)
    if start < steps:
        return None
    return (
        f"tokenizer.loss.disc_start={loss.disc_start} starts the adversarial term at step {start}, after the run's "
        f"last (tokenizer.train.steps={steps}): it never trains; lower disc_start (0.5 starts it half way), or "
        "turn it off with tokenizer.loss.adversarial_weight=0"
    )


@dataclass
class Tokenizer:
    """An autoencoder plugin and a quantizer plugin used together.

    ``rebase_3HW`` (in [0, 1] units, or None): the family's no-contact image minus this sensor's, for a
    tokenizer adapted to a sensor that looks unlike its family.  Its images are moved onto the family's
    background before encoding and back after decoding, so a contact keeps the codes it has on the
    family's sensor, and the family generator's codes decode in the new sensor's look
    (:func:`vqtouch.plugins.adaptation.adapt_tokenizer` with ``rebase``)."""

    autoencoder: Autoencoder
    quantizer: Quantizer
    rebase_3HW: torch.Tensor | None = None

    @property
    def device(self) -> torch.device:
        """The device the tokenizer's weights are on."""
        return next(self.autoencoder.parameters()).device

    def to(self, device: torch.device | str) -> Tokenizer:
        """Both parts (and the rebase image) moved to ``device``."""
        self.autoencoder.to(device)
        self.quantizer.to(device)
        if self.rebase_3HW is not None:
            self.rebase_3HW = self.rebase_3HW.to(device)
        return self

    def _into_family(self, images_B3HW: torch.Tensor) -> torch.Tensor:
        return images_B3HW if self.rebase_3HW is None else images_B3HW + self.rebase_3HW.to(images_B3HW)

    def _out_of_family(self, images_B3HW: torch.Tensor) -> torch.Tensor:
        return images_B3HW if self.rebase_3HW is None else images_B3HW - self.rebase_3HW.to(images_B3HW)

    def reconstruct(self, images_B3HW: torch.Tensor) -> tuple[torch.Tensor, Any]:
        """Images in [0, 1] -> reconstructions in [0, 1] (clamped) and the quantizer output."""
        output = self.quantizer(self.autoencoder.encode(self._into_family(images_B3HW) * 2 - 1))
        decoded = (self.autoencoder.decode(output.quantized_BDhw).float() + 1) / 2
        return self._out_of_family(decoded).clamp(0, 1), output

    def encode_codes(self, images_B3HW: torch.Tensor) -> torch.Tensor:
        """Images in [0, 1] -> integer codes (B, h, w) (the quantizer's code grid)."""
        return self.quantizer(self.autoencoder.encode(self._into_family(images_B3HW) * 2 - 1)).codes_Bhw

    def decoder_parameters(self) -> list[nn.Parameter]:
        """The autoencoder's parameters that decoding a latent grid uses (what decoder-only adaptation
        trains, leaving the encoder and the codebook, and so every image's codes, as they were).  Found
        by differentiating one decode, so it holds for any autoencoder plugin."""
        from vqtouch.core.image_size import image_hw

        autoencoder = self.autoencoder
        with torch.no_grad():
            latents = autoencoder.encode(
                torch.zeros(1, 3, *image_hw(autoencoder.vqtouch_spec.context.image_size), device=self.device)
            )
        params = list(autoencoder.parameters())
        with torch.enable_grad():
            grads = torch.autograd.grad(autoencoder.decode(latents).float().sum(), params, allow_unused=True)
        return [param for param, grad in zip(params, grads) if grad is not None]

    def decode_codes(self, codes_Bhw: torch.Tensor) -> torch.Tensor:
        """Integer codes (B, h, w) -> images in [0, 1] (clamped), e.g. for generated codes."""
        decoded = (self.autoencoder.decode(self.quantizer.lookup(codes_Bhw)).float() + 1) / 2
        return self._out_of_family(decoded).clamp(0, 1)

    def eval(self) -> Tokenizer:
        """Both parts in eval mode."""
        self.autoencoder.eval()
        self.quantizer.eval()
        return self


class TokenizerTask:
    """The tokenizer objective as a :class:`vqtouch.plugins.training.trainer.TrainingTask`."""

    def __init__(
        self,
        tokenizer: Tokenizer,
        loss: TokenizerLossConfig,
        discriminator: nn.Module | None = None,
        perceptual: nn.Module | None = None,
    ) -> None:
        self.tokenizer = tokenizer
        self.loss = loss
        self.discriminator = discriminator if loss.adversarial_weight > 0 else None
        self.perceptual = perceptual if loss.perceptual_weight > 0 else None
        self.modules: dict[str, nn.Module] = {"autoencoder": tokenizer.autoencoder, "quantizer": tokenizer.quantizer}
        if self.discriminator is not None:
            self.modules["discriminator"] = self.discriminator

    def parameter_groups(self) -> dict[str, list[nn.Parameter] | list[dict[str, Any]]]:
        """The generator (autoencoder + quantizer, with the autoencoder's learning-rate scales, e.g.
        the deformable offset branches) and, when used, the discriminator."""
        scaled = [
            (scale, [p for p in params if p.requires_grad])
            for scale, params in self.tokenizer.autoencoder.learning_rate_scales()
        ]
        scaled_ids = {id(p) for _, params in scaled for p in params}
        base = [
            p
            for name in ("autoencoder", "quantizer")
            for p in self.modules[name].parameters()
            if p.requires_grad and id(p) not in scaled_ids
        ]
        groups: dict[str, list] = {
            "generator": [{"params": base}]
            + [{"params": params, "lr_scale": scale} for scale, params in scaled if params]
        }
        if self.discriminator is not None:
            groups["discriminator"] = list(self.discriminator.parameters())
        return groups

    def validation_loss(self, batch: dict[str, Any], trainer: Any) -> torch.Tensor:
        """(B,) held-out score of each sample: the mean absolute pixel error of its reconstruction (the
        training L1, in [-1, 1] units), from the eval-mode tokenizer; the trainer keeps the
        checkpoint where its mean is lowest."""
        self.tokenizer.eval()
        self.tokenizer.autoencoder.reset_randomness()
        images = batch["tactile"]
        with trainer.autocast():
            reconstruction, _ = self.tokenizer.reconstruct(images)
        return 2 * (reconstruction.float() - images).abs().flatten(1).mean(1)

    def training_step(self, batch: dict[str, Any], step: int, trainer: Any) -> dict[str, float]:
        """One generator step, then (from disc_start) one discriminator step."""
        images = batch["tactile"] * 2 - 1
        encoder, quantizer = self.tokenizer.autoencoder, self.tokenizer.quantizer
        encoder.train()
        quantizer.train()
        with trainer.autocast():
            latents = encoder.encode(images)
        output = quantizer(latents)  # fp32 inside, whatever the autocast
        with trainer.autocast():
            reconstruction = encoder.decode(output.quantized_BDhw)
        reconstruction = reconstruction.float()
        l1 = (images - reconstruction).abs().mean()
        nll = self.loss.l1_weight * l1
        scalars = {
            "l1": float(l1.detach()),
            "vq_loss": float(output.loss.detach()),
            "perplexity": float(output.perplexity),
        }
        if self.perceptual is not None:
            perceptual = self.perceptual(reconstruction, images).mean()
            nll = nll + self.loss.perceptual_weight * perceptual
            scalars["perceptual"] = float(perceptual.detach())
        total = nll + self.loss.codebook_weight * output.loss
        adversarial_on = self.discriminator is not None and step >= disc_start_step(
            self.loss.disc_start, trainer.config.steps
        )
        if adversarial_on:
            with trainer.autocast():
                generator_loss = -self.discriminator(reconstruction).float().mean()
            weight = adaptive_weight(nll, generator_loss, encoder.last_layer_weight(), self.loss.adaptive_weight_max)
            total = total + weight * self.loss.adversarial_weight * generator_loss
            scalars |= {"g_loss": float(generator_loss.detach()), "adaptive_weight": float(weight)}
        trainer.optimize("generator", total)
        scalars["loss"] = float(total.detach())
        if adversarial_on:
            with trainer.autocast():
                logits_real = self.discriminator(images)
                logits_fake = self.discriminator(reconstruction.detach())
            disc_loss = hinge_discriminator_loss(logits_real, logits_fake)
            trainer.optimize("discriminator", disc_loss)
            scalars["d_loss"] = float(disc_loss.detach())
        offsets = getattr(encoder, "offset_magnitude", lambda: None)()
        if offsets is not None:
            scalars["mean_abs_offset"] = offsets
        return scalars


@torch.no_grad()
def evaluate_reconstruction(
    tokenizer: Tokenizer,
    dataset: Any,
    metrics: Mapping[str, Metric] | MetricSet,
    *,
    batch_size: int = 32,
    device: torch.device | str = "cpu",
    keep: int = 8,
    background_3HW: torch.Tensor | None = None,
) -> dict[str, Any]:
    """Reconstruct every sample of ``dataset``; metrics, codebook usage, perplexity and speed.

    Metrics are scored through a :class:`~vqtouch.core.MetricSet`: unrounded values by name, and
    ``"skipped"`` with the reason of each metric that cannot run here.  Given the data's
    no-contact image ``background_3HW``, each metric also scores that image against every input
    (``background_*``: what a tokenizer that draws only the background gets), and both are scored
    on the contact region (``contact_*``, ``background_contact_*``, ``contact_fraction``; see
    :class:`~vqtouch.plugins.evaluation.contact.ContactRegionScores`).

    Returns the scores and, under ``"examples"``, the first ``keep`` (original, reconstruction)
    pairs for a picture.  Raises :class:`NothingToEvaluateError` when ``dataset`` is empty (a
    caller may then skip the evaluation and say why), and :class:`VqtouchError` when the
    reconstructions are not finite: no metric can score them.
    """

    if len(dataset) == 0:
        raise NothingToEvaluateError(
            "nothing to evaluate: the dataset has no samples (a run's held-out split is empty when "
            "data.val_fraction=0); evaluate other samples with `vqtouch evaluate reconstruction --split all` or "
            "--dataset"
        )
    tokenizer.eval()
    tokenizer.autoencoder.reset_randomness()
    tokenizer.quantizer.reset_usage()
    metrics = metrics if isinstance(metrics, MetricSet) else MetricSet(metrics)
    metrics.reset()
    background = background_3HW.detach().float().cpu().unsqueeze(0) if background_3HW is not None else None
    contact = ContactRegionScores(background) if background is not None else None

    originals, reconstructions, seconds, count = _reconstruct_batches(
        tokenizer, dataset, metrics, contact, background, batch_size=batch_size, device=device, keep=keep
    )
    scores: dict[str, Any] = metrics.scores(digits=None)
    if background is not None:
        # The metrics again, on the background against every input (a second pass: the metrics
        # accumulate one stream at a time).
        metrics.reset()
        for images in _tactile_batches(dataset, batch_size):
            metrics.update(background.expand_as(images), images)
        scores |= metrics.scores("background_", digits=None)
        scores |= contact.scores()
    scores |= _codebook_scores(tokenizer)
    scores |= {
        "samples": count,
        "reconstructions_per_second": count / max(seconds, 1e-9),
        "examples": (torch.stack(originals), torch.stack(reconstructions)),
    }
    return scores


def _tactile_batches(dataset: Any, batch_size: int) -> Iterator[torch.Tensor]:
    """The tactile images of ``dataset`` in order, ``batch_size`` at a time."""
    for start in range(0, len(dataset), batch_size):
        yield collate_samples([dataset[i] for i in range(start, min(start + batch_size, len(dataset)))])["tactile"]


def _reconstruct_batches(
    tokenizer: Tokenizer,
    dataset: Any,
    metrics: MetricSet,
    contact: ContactRegionScores | None,
    background: torch.Tensor | None,
    *,
    batch_size: int,
    device: torch.device | str,
    keep: int,
) -> tuple[list[torch.Tensor], list[torch.Tensor], float, int]:
    """Reconstruct every batch, updating ``metrics`` (and ``contact``, with the background beside
    the reconstructions); the first ``keep`` originals and reconstructions, the seconds spent
    reconstructing and the number of images."""
    originals, reconstructions = [], []
    seconds, count = 0.0, 0
    for images in _tactile_batches(dataset, batch_size):
        images = images.to(device)
        tic = time.perf_counter()
        reconstruction, output = tokenizer.reconstruct(images)
        seconds += time.perf_counter() - tic
        if not torch.isfinite(reconstruction).all():
            # Checked here, before a metric sees them: the cause is the tokenizer, not the images.
            raise VqtouchError(_non_finite_message(tokenizer))
        count += len(images)
        metrics.update(reconstruction.cpu(), images.cpu())
        if contact is not None:
            contact.update({"": reconstruction, "background_": background.expand_as(images.cpu())}, images)
        if len(originals) < keep:
            originals.extend(images[: keep - len(originals)].cpu())
            reconstructions.extend(reconstruction[: keep - len(reconstructions)].cpu())
    return originals, reconstructions, seconds, count


def _codebook_scores(tokenizer: Tokenizer) -> dict[str, Any]:
    """How much of its codebook the tokenizer used since its usage was reset (empty without one)."""
    counts_K = tokenizer.quantizer.usage_counts()
    if counts_K is None:
        return {}
    counts_K = counts_K.cpu()
    return {
        "codebook_usage": float((counts_K > 0).double().mean()),
        "codes_used": int((counts_K > 0).sum()),
        "perplexity": float(perplexity_of_counts(counts_K, dtype=torch.float64)),
    }


def _non_finite_message(tokenizer: Tokenizer) -> str:
    """Why a tokenizer's reconstructions are NaN/Inf: which of its weights are not finite, if any."""
    step = getattr(tokenizer.autoencoder, "vqtouch_step", None)  # set when loaded from a checkpoint
    which = f" (checkpoint step {step})" if step is not None else ""
    broken = []
    for name, module in (("autoencoder", tokenizer.autoencoder), ("quantizer", tokenizer.quantizer)):
        bad = [
            key
            for key, value in module.state_dict().items()
            if value.is_floating_point() and not torch.isfinite(value).all()
        ]
        if bad:
            broken.append(f"{name}: {len(bad)} tensor(s), first {bad[0]!r}")
    cause = (
        f"its weights are not finite ({'; '.join(broken)})"
        if broken
        else "its weights are finite, so a value overflows inside the network"
    )
    return (
        f"the tokenizer{which} produced NaN/Inf reconstructions; {cause}; evaluate an earlier checkpoint with "
        "--step, or retrain with a lower tokenizer.train.learning_rate"
    )


def tokenizer_task(
    tokenizer: Tokenizer, loss: TokenizerLossConfig, device: torch.device, discriminator: torch.nn.Module | None = None
) -> TokenizerTask:
    """The tokenizer objective ``loss`` for ``tokenizer``, with its perceptual network built on
    ``device`` when the loss uses one (training and adaptation both start here)."""
    from .perceptual import build_perceptual_loss

    perceptual = None
    if loss.perceptual != "none" and loss.perceptual_weight > 0:
        perceptual = build_perceptual_loss(
            loss.perceptual, loss.lpips_backbone, loss.lpips_heads, effnet_image_size=loss.perceptual_image_size
        ).to(device)
    return TokenizerTask(tokenizer, loss, discriminator, perceptual)

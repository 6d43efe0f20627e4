"""Named evaluation protocols: which metrics, at which image size, on which pairs.

Numbers from different protocols do not compare (resolution alone moves SSIM and PSNR), so every
score file names its protocol.  Two are built in:

- ``published``: the tactile-generation papers' protocol (TextToucher's ``metrics/metric.py``, used
  for HCT / SSVTP / Touch and Go tables): generated and real images resized to 512 x 512 (bicubic,
  Pillow's default resize), LPIPS with the VGG trunk (torchmetrics, inputs in [0, 1] normalised to
  [-1, 1]), SSIM with data range 1 (Gaussian 11 x 11, sigma 1.5), and PSNR as torchmetrics'
  default reduction: one value of the squared error pooled over every pixel of every pair, data
  range 1.  Pairs are matched by id (TextToucher pairs by sorted file name, which pairs the same
  files when generated and real share names).  Older torchmetrics releases took PSNR's range from
  the data; with ground truth spanning [0, 1] that is the same number.
- ``default``: vqtouch's protocol for the embedded data, at the images' own size (64 or 128 px):
  per-image SSIM and PSNR averaged over pairs, MS-SSIM (as many of the five scales as the size
  allows), LPIPS (VGG) when its weights file is present, and the offline distribution metrics
  ``fd_effnetlite0`` and ``kid_effnetlite0``.

Where the two must agree they do: at 512 px, on pairs of equal per-image error, SSIM is the same
number and the pooled PSNR equals the mean per-image PSNR (tests/test_protocols.py).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from pydantic import BaseModel, ConfigDict, Field

from vqtouch.core import ConfigError, PluginHost
from vqtouch.core.errors import unknown_name_message

if TYPE_CHECKING:  # torch is imported where images are resized, so that the commands' parsers stay light
    import torch

    from vqtouch.plugins.evaluation.metric_set import MetricSet


class EvaluationProtocol(BaseModel):
    """One way of scoring generated against real images; its name goes into every score file."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field(description="The protocol's name, written next to its numbers.")
    description: str = Field(description="What it does, in a sentence a reader of a results table needs.")
    image_size: int | None = Field(
        None,
        ge=16,
        le=4096,
        description="Side both image sets are resized to (bicubic, no crop) before "
        "scoring; None: scored at their own size.",
    )
    metrics: tuple[dict[str, Any], ...] = Field(description="The metric plugin configs, in table order.")

    def prepare(self, images_B3HW: torch.Tensor) -> torch.Tensor:
        """``images_B3HW`` (in [0, 1]) at the protocol's size: bicubic with antialiasing, clamped to [0, 1]
        (bicubic overshoots at edges); unchanged when the protocol keeps sizes or they already match."""
        if self.image_size is None or tuple(images_B3HW.shape[-2:]) == (self.image_size, self.image_size):
            return images_B3HW
        import torch.nn.functional as F

        resized = F.interpolate(
            images_B3HW.float(),
            size=(self.image_size, self.image_size),
            mode="bicubic",
            antialias=True,
            align_corners=False,
        )
        return resized.clamp(0, 1)

    def build_metrics(self, host: PluginHost, overrides: Mapping[str, Mapping[str, Any]] | None = None) -> MetricSet:
        """The protocol's metrics, built by ``host``; ``overrides``: extra options by metric name (e.g.
        ``{"lpips": {"weights": PATH}}``).  A metric whose weights are missing is built skipped."""
        from vqtouch.plugins.evaluation.metric_set import MetricSet

        overrides = overrides or {}
        unknown = sorted(set(overrides) - {metric["name"] for metric in self.metrics})
        if unknown:
            raise ConfigError(
                f"protocol {self.name!r} has no metric {unknown[0]!r}; its metrics: "
                f"{', '.join(metric['name'] for metric in self.metrics)}"
            )
        return MetricSet(
            (metric["name"], host.build("metric", {**metric, **overrides.get(metric["name"], {})}))
            for metric in self.metrics
        )

    def score(
        self, metrics: MetricSet, generated_B3HW: torch.Tensor, real_B3HW: torch.Tensor, prefix: str = ""
    ) -> dict[str, Any]:
        """``metrics`` (from :meth:`build_metrics`) of generated image i against real image i, both prepared."""
        if generated_B3HW.shape[0] != real_B3HW.shape[0]:
            raise ConfigError(
                f"protocol {self.name!r} scores pairs: got {generated_B3HW.shape[0]} generated and "
                f"{real_B3HW.shape[0]} real images"
            )
        return metrics.score(self.prepare(generated_B3HW), self.prepare(real_B3HW), prefix)


PROTOCOLS: dict[str, EvaluationProtocol] = {
    protocol.name: protocol
    for protocol in (
        EvaluationProtocol(
            name="published",
            description="the tactile-generation papers' protocol: 512 x 512 (bicubic), LPIPS-VGG, SSIM (data range "
            "1), PSNR of the pooled error, pairs by id",
            image_size=512,
            metrics=({"name": "ssim"}, {"name": "psnr", "pooled": True}, {"name": "lpips", "backbone": "vgg"}),
        ),
        EvaluationProtocol(
            name="default",
            description="vqtouch's protocol for the embedded data: own size, per-image SSIM / PSNR / MS-SSIM "
            "averaged, LPIPS-VGG when its weights are present, fd_effnetlite0 and kid_effnetlite0",
            image_size=None,
            metrics=(
                {"name": "ssim"},
                {"name": "psnr"},
                {"name": "ms_ssim"},
                {"name": "lpips", "backbone": "vgg"},
                {"name": "fd_effnetlite0"},
                {"name": "kid_effnetlite0"},
            ),
        ),
    )
}


def get_protocol(name: str) -> EvaluationProtocol:
    """The protocol called ``name``; an unknown name is a ConfigError listing the protocols."""
    if name not in PROTOCOLS:
        raise ConfigError(unknown_name_message("evaluation protocol", name, sorted(PROTOCOLS)))
    return PROTOCOLS[name]


def pair_by_id(generated: Mapping[str, Any], real: Mapping[str, Any]) -> list[str]:
    """The ids present in both, sorted; a ConfigError naming a few unmatched ids when the sets differ
    (pairing by position would silently score image i against some other contact)."""
    only_generated = sorted(set(generated) - set(real))
    only_real = sorted(set(real) - set(generated))
    if only_generated or only_real:

        def few(ids: list[str]) -> str:
            return ", ".join(ids[:3]) + (f" and {len(ids) - 3} more" if len(ids) > 3 else "")

        parts = (
            [f"{len(only_generated)} generated image(s) without a real one ({few(only_generated)})"]
            if only_generated
            else []
        ) + ([f"{len(only_real)} real image(s) without a generated one ({few(only_real)})"] if only_real else [])
        raise ConfigError(
            f"pairs are matched by id (file path without extension): {'; '.join(parts)}; give both "
            "folders the same file names"
        )
    return sorted(generated)

"""The behaviour each model base class promises: sensor families, conditioners, autoencoders,
quantizers, discriminators, generators and samplers."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import torch

from vqtouch.core.components import (
    Autoencoder,
    BuildContext,
    Conditioner,
    ConditionTokens,
    Discriminator,
    Generator,
    Quantizer,
    QuantizerOutput,
    Sampler,
    SensorFamily,
)
from vqtouch.core.errors import MissingWeightsError, VqtouchError
from vqtouch.core.image_size import ImageSize, image_hw, pixel_centres_mm, size_text
from ._support import DEFAULT_CONTEXT, _assert_same, _call, _generator, _images, _latents, _require, _skip

if TYPE_CHECKING:
    from vqtouch.core.plugin_manager import PluginHost


# -- behaviour of each base class ----------------------------------------------------------------------


def press_height_maps(batch: int, size: ImageSize, field_of_view_mm: float, depth_mm: float = 1.0) -> torch.Tensor:
    """(batch, H, W) indentations in mm (``size`` S or (H, W)): a sphere pressed ``depth_mm`` deep, a
    little off-centre and a little deeper in each row, drawn at the physical scale of
    ``field_of_view_mm`` (the side of the square it covers, with square pixels along the shorter side)."""
    height, width = image_hw(size)
    ys, xs = pixel_centres_mm(
        height, width, tuple(field_of_view_mm * side / min(height, width) for side in (height, width))
    )
    radius = field_of_view_mm / 4
    maps = []
    for row in range(batch):
        shift = field_of_view_mm * 0.05 * row
        depth = depth_mm * (1 + 0.25 * row)
        cap = (radius**2 - (xs - shift) ** 2 - (ys + shift / 2) ** 2).clamp_min(0).sqrt() - (radius - depth)
        maps.append(cap.clamp_min(0))
    return torch.stack(maps)


def check_sensor_family(sensor: SensorFamily, context: BuildContext | None = None, *, label: str = "sensor") -> None:
    """A sensor family renders (B, H, W) mm height maps to finite (B, 3, H, W) images in [0, 1],
    deterministically for a fixed generator, shows a contact, stays finite at extremes (flat, a deep
    sharp-edged press) and declares a sensible field of view, sensor id and reference frames."""
    context = context or DEFAULT_CONTEXT
    height, width = image_hw(context.image_size)
    fov = sensor.field_of_view_mm
    _require(
        isinstance(fov, (int, float)) and math.isfinite(fov) and fov > 0,
        label,
        f"field_of_view_mm must be a positive number of mm, got {fov!r}",
    )
    _require(isinstance(sensor.sensor_id, str), label, f"sensor_id must be a str, got {sensor.sensor_id!r}")
    sensor.eval()
    press = press_height_maps(2, context.image_size, fov)
    flat = torch.zeros(2, height, width)
    deep = torch.zeros(2, height, width)
    deep[:, height // 4 : 3 * height // 4, width // 4 : 3 * width // 4] = 50.0
    with torch.no_grad():
        rendered = {
            what: _call(
                label, f"render({what} height maps)", lambda h=heights: sensor.render(h, generator=_generator(0))
            )
            for what, heights in (("pressed", press), ("flat", flat), ("deep", deep))
        }
        again = _call(label, "render(pressed) again", lambda: sensor.render(press, generator=_generator(0)))
    for what, images in rendered.items():
        _require(
            isinstance(images, torch.Tensor), label, f"render({what}) returned {type(images).__name__}, not a tensor"
        )
        _require(
            tuple(images.shape) == (2, 3, height, width),
            label,
            f"render of (2, {height}, {width}) {what} height maps returned shape {tuple(images.shape)}; "
            f"expected (2, 3, {height}, {width})",
        )
        _require(images.dtype.is_floating_point, label, f"render({what}) returned dtype {images.dtype}")
        _require(bool(torch.isfinite(images).all()), label, f"render({what}) has NaN or Inf values")
        low, high = float(images.min()), float(images.max())
        _require(
            low >= 0.0 and high <= 1.0,
            label,
            f"render({what}) has values outside [0, 1] (min {low:.4g}, max {high:.4g})",
        )
    _require(
        torch.equal(rendered["pressed"], again),
        label,
        "render is not deterministic for a fixed generator: two calls with "
        "torch.Generator().manual_seed(0) gave different images (draw noise from `generator`)",
    )
    _require(
        float((rendered["pressed"] - rendered["flat"]).abs().max()) > 1e-3,
        label,
        "a 1 mm press renders the same image as no contact: the height map does not reach the image",
    )
    frames = _call(label, f"reference_frames({height}, {width})", lambda: sensor.reference_frames(height, width))
    if frames is not None:
        _require(
            isinstance(frames, torch.Tensor) and frames.ndim == 4 and tuple(frames.shape[1:]) == (3, height, width),
            label,
            f"reference_frames({height}, {width}) must be None or (N, 3, {height}, {width}), got "
            f"{tuple(getattr(frames, 'shape', ()))}",
        )
        _require(
            bool(torch.isfinite(frames).all()) and float(frames.min()) >= 0 and float(frames.max()) <= 1,
            label,
            "reference_frames has values outside [0, 1] or non-finite values",
        )
    extent = _call(label, f"imaged_extent_mm({height}, {width})", lambda: sensor.imaged_extent_mm(height, width))
    _require(
        isinstance(extent, tuple)
        and len(extent) == 2
        and all(isinstance(side, (int, float)) and math.isfinite(side) and side > 0 for side in extent),
        label,
        f"imaged_extent_mm({height}, {width}) must be a (rows, columns) pair of positive mm, got {extent!r}",
    )


def example_condition(conditioner: Conditioner, batch: int, context: BuildContext | None = None) -> Any:
    """A fixed batch of raw conditions for ``conditioner``, chosen from its ``sample_key`` the way a
    collated dataset batch holds them: ``label`` integer labels (B,) below the context's class
    count, ``tactile``/``tactile_source``/``visual`` images (B, channels, H, W) in [0, 1], ``text`` a
    list of B strings.
    Returns None for any other key (pass ``condition=`` to the checks then)."""
    context = context or DEFAULT_CONTEXT
    key = conditioner.sample_key
    if key == "label":
        return torch.arange(batch) % max(context.num_classes, 1)
    if key in ("tactile", "tactile_source", "visual"):
        channels = context.channels if key.startswith("tactile") else 3
        return torch.rand(batch, channels, *image_hw(context.image_size), generator=_generator(1))
    if key == "text":
        texts = ["a smooth sphere pressed into the gel", "a coarse woven fabric", "a sharp metal edge"]
        return [texts[i % len(texts)] for i in range(batch)]
    if key == "sensor_index":  # a sensor tag's rows: which sensor each is
        return torch.arange(batch) % max(int(getattr(conditioner, "num_sensors", 1)), 1)
    return None


def _check_conditioner_attributes(conditioner: Conditioner, context: BuildContext, label: str) -> None:
    """The conditioner names the sample key it reads and emits ``num_tokens`` tokens of the context's width."""
    key = conditioner.sample_key
    _require(
        isinstance(key, str) and key not in ("", "sensor", "id"),
        label,
        f"sample_key {key!r} is not a condition: name the sample entry it reads (label, tactile, "
        "tactile_source, visual, text, or another a dataset provides) or the condition it derives",
    )
    _require(
        conditioner.cond_dim == context.cond_dim,
        label,
        f"emits tokens of width {conditioner.cond_dim}, but the context asks for cond_dim={context.cond_dim}",
    )
    _require(
        isinstance(conditioner.num_tokens, int) and conditioner.num_tokens >= 1,
        label,
        f"num_tokens must be a positive int, got {conditioner.num_tokens!r}",
    )


def _check_condition_tokens(label: str, what: str, tokens: Any, shape: tuple[int, ...], batch: int) -> None:
    """``tokens`` is :class:`ConditionTokens` of ``shape``, finite, with a bool null flag per row."""
    _require(
        isinstance(tokens, ConditionTokens), label, f"{what} returned {type(tokens).__name__}, not ConditionTokens"
    )
    _require(
        tuple(tokens.tokens_BND.shape) == shape,
        label,
        f"{what} returned tokens of shape {tuple(tokens.tokens_BND.shape)}; expected {shape}",
    )
    _require(bool(torch.isfinite(tokens.tokens_BND).all()), label, f"{what} returned NaN or Inf tokens")
    _require(
        tokens.is_null_B.dtype == torch.bool and tuple(tokens.is_null_B.shape) == (batch,),
        label,
        f"{what} returned is_null_B of dtype {tokens.is_null_B.dtype} and shape "
        f"{tuple(tokens.is_null_B.shape)}; expected bool ({batch},)",
    )


def _check_null_tokens(
    conditioner: Conditioner, label: str, out: Any, dropped: Any, null: Any, drop_B: torch.Tensor
) -> None:
    """Dropped rows (and ``null(B)``) carry exactly the learned null tokens, flagged; other rows are unchanged."""
    null_ND = conditioner.null_tokens_ND.detach()
    _require(not bool(out.is_null_B.any()), label, "forward without a drop mask flagged rows as null")
    _require(
        torch.equal(dropped.is_null_B, drop_B),
        label,
        "forward(condition, drop_mask) must flag exactly the dropped rows in is_null_B",
    )
    _require(
        torch.equal(dropped.tokens_BND[0], null_ND.to(dropped.tokens_BND.dtype)),
        label,
        "a dropped row does not carry the learned null tokens (null_tokens_ND)",
    )
    _require(
        torch.equal(dropped.tokens_BND[1:], out.tokens_BND[1:]),
        label,
        "dropping row 0 changed the tokens of the rows that were not dropped",
    )
    _require(
        bool(null.is_null_B.all()) and all(torch.equal(row, null_ND) for row in null.tokens_BND),
        label,
        "null(B) must return the learned null tokens for every row, all flagged in is_null_B",
    )


def check_conditioner(
    conditioner: Conditioner, context: BuildContext | None = None, *, condition: Any = None, label: str = "conditioner"
) -> None:
    """A conditioner reads a documented sample key and turns a batch of conditions into finite tokens
    (B, num_tokens, cond_dim) with cond_dim the context's; rows of the drop mask get exactly the
    learned null tokens and the other rows are unchanged; ``null(B)`` is the null tokens, flagged."""
    context = context or DEFAULT_CONTEXT
    key = conditioner.sample_key
    _check_conditioner_attributes(conditioner, context, label)
    batch = 3
    if condition is None:
        condition = example_condition(conditioner, batch, context)
        _require(
            condition is not None,
            label,
            f"no example condition for sample_key {key!r}; pass condition=<a batch of {batch}>",
        )
    else:
        batch = len(condition)
    _require(
        conditioner.condition_of({key: condition, "id": ["x"] * batch}) is condition,
        label,
        f"condition_of(batch) must return batch[{key!r}]",
    )
    conditioner.eval()
    shape = (batch, conditioner.num_tokens, context.cond_dim)
    with torch.no_grad():
        out = _call(label, "forward(condition)", lambda: conditioner(condition))
        drop_B = torch.zeros(batch, dtype=torch.bool)
        drop_B[0] = True
        dropped = _call(label, "forward(condition, drop_mask)", lambda: conditioner(condition, drop_B))
        null = _call(label, f"null({batch})", lambda: conditioner.null(batch))
    for what, tokens in (("forward", out), ("forward with a drop mask", dropped), ("null", null)):
        _check_condition_tokens(label, what, tokens, shape, batch)
    _check_null_tokens(conditioner, label, out, dropped, null, drop_B)
    single = example_condition(conditioner, 1, context)
    if single is not None:  # batch 1 (a single condition at generation time) must work too
        with torch.no_grad():
            one = _call(label, "forward(condition of batch 1)", lambda: conditioner(single))
        _require(
            tuple(one.tokens_BND.shape) == (1, *shape[1:]) and bool(torch.isfinite(one.tokens_BND).all()),
            label,
            f"a batch of 1 gave tokens of shape {tuple(one.tokens_BND.shape)} (or non-finite ones)",
        )


def check_autoencoder(
    autoencoder: Autoencoder, context: BuildContext | None = None, *, label: str = "autoencoder"
) -> None:
    """An autoencoder maps images (B, C, H, W) in [-1, 1] to finite latents (B, latent_channels, H/f, W/f)
    and back to (B, C, H, W); decode is a pure function of its input, ``reset_randomness`` makes an
    evaluation repeat exactly and ``context_facts`` reports the latent width."""
    context = context or DEFAULT_CONTEXT
    factor, width = autoencoder.downsample_factor, autoencoder.latent_channels
    (rows, cols), size = image_hw(context.image_size), size_text(context.image_size)
    _require(
        isinstance(factor, int) and factor >= 1 and rows % factor == 0 and cols % factor == 0,
        label,
        f"downsample_factor {factor!r} must be a positive int dividing the image size {size}",
    )
    _require(isinstance(width, int) and width >= 1, label, f"latent_channels must be a positive int, got {width!r}")
    _require(
        autoencoder.context_facts().get("latent_dim") == width,
        label,
        f"context_facts() must report latent_dim={width} (its latent_channels) for the quantizer",
    )
    images = _images(2, context)
    autoencoder.eval()
    with torch.no_grad():
        autoencoder.reset_randomness()
        latents = _call(label, "encode(images)", lambda: autoencoder.encode(images))
        _require(
            tuple(latents.shape) == (2, width, rows // factor, cols // factor),
            label,
            f"encode of (2, {context.channels}, {rows}, {cols}) returned {tuple(latents.shape)}; expected "
            f"(2, {width}, {rows // factor}, {cols // factor})",
        )
        _require(bool(torch.isfinite(latents).all()), label, "encode returned NaN or Inf latents")
        decoded = _call(label, "decode(latents)", lambda: autoencoder.decode(latents))
        _require(
            tuple(decoded.shape) == tuple(images.shape),
            label,
            f"decode returned {tuple(decoded.shape)}; expected {tuple(images.shape)}",
        )
        _require(bool(torch.isfinite(decoded).all()), label, "decode returned NaN or Inf images")
        _assert_same(
            decoded,
            _call(label, "decode(latents) again", lambda: autoencoder.decode(latents)),
            label,
            "decode is not a pure function of its input (two calls on the same latents differ)",
        )
        autoencoder.reset_randomness()
        repeated = _call(label, "encode after reset_randomness", lambda: autoencoder.decode(autoencoder.encode(images)))
        _assert_same(
            decoded,
            repeated,
            label,
            "decode(encode(x)) differs after reset_randomness(): evaluations must repeat exactly",
        )


def check_quantizer(quantizer: Quantizer, context: BuildContext | None = None, *, label: str = "quantizer") -> None:
    """A quantizer maps latents (B, embedding_dim, h, w) to a :class:`QuantizerOutput` of the same
    shape with integer codes (B, h, w) in [0, codebook_size), a finite scalar loss and a perplexity
    in [1, codebook_size]; it follows the context's latent width and reports its codebook size; one
    with a codebook counts usage since ``reset_usage`` and ``lookup(codes)`` gives the quantized latents."""
    context = context or DEFAULT_CONTEXT
    dim, size = quantizer.embedding_dim, quantizer.codebook_size
    _require(isinstance(dim, int) and dim >= 1, label, f"embedding_dim must be a positive int, got {dim!r}")
    _require(isinstance(size, int) and size >= 1, label, f"codebook_size must be a positive int, got {size!r}")
    if context.latent_dim:
        _require(
            dim == context.latent_dim,
            label,
            f"embedding_dim {dim} does not follow the context's "
            f"latent_dim {context.latent_dim} (the autoencoder's latents)",
        )
    _require(
        quantizer.context_facts().get("codebook_size") == size,
        label,
        f"context_facts() must report codebook_size={size}",
    )
    latents = _latents(quantizer)
    quantizer.eval()
    with torch.no_grad():
        quantizer.reset_usage()
        out = _call(label, "forward(latents)", lambda: quantizer(latents))
    _require(isinstance(out, QuantizerOutput), label, f"forward returned {type(out).__name__}, not QuantizerOutput")
    _require(
        tuple(out.quantized_BDhw.shape) == tuple(latents.shape),
        label,
        f"quantized latents have shape {tuple(out.quantized_BDhw.shape)}; expected {tuple(latents.shape)}",
    )
    _require(bool(torch.isfinite(out.quantized_BDhw).all()), label, "quantized latents have NaN or Inf values")
    codes = out.codes_Bhw
    _require(
        not codes.dtype.is_floating_point and codes.dtype != torch.bool and tuple(codes.shape) == (2, 4, 4),
        label,
        f"codes must be integers of shape (2, 4, 4), got {codes.dtype} {tuple(codes.shape)}",
    )
    _require(
        int(codes.min()) >= 0 and int(codes.max()) < size,
        label,
        f"codes must lie in [0, {size}); got min {int(codes.min())}, max {int(codes.max())}",
    )
    for what, value in (("loss", out.loss), ("perplexity", out.perplexity)):
        _require(
            isinstance(value, torch.Tensor) and value.numel() == 1 and bool(torch.isfinite(value).all()),
            label,
            f"{what} must be a finite scalar tensor, got {value!r}",
        )
    perplexity = float(out.perplexity)
    _require(1 - 1e-4 <= perplexity <= size * (1 + 1e-4), label, f"perplexity {perplexity:.4g} is outside [1, {size}]")
    usage = quantizer.usage_counts()
    if usage is not None:
        _require(
            tuple(usage.shape) == (size,) and int(usage.sum()) == codes.numel(),
            label,
            f"usage_counts() after reset_usage() and one forward of {codes.numel()} latents must be ({size},) "
            f"summing to {codes.numel()}, got shape {tuple(usage.shape)} summing to {int(usage.sum())}",
        )
        quantizer.reset_usage()
        _require(int(quantizer.usage_counts().sum()) == 0, label, "reset_usage() does not forget the usage counts")
        with torch.no_grad():
            looked_up = _call(label, "lookup(codes)", lambda: quantizer.lookup(codes))
        _assert_same(
            out.quantized_BDhw,
            looked_up,
            label,
            "lookup(codes) does not give the quantized latents forward returned for those codes",
        )


def check_discriminator(
    discriminator: Discriminator, context: BuildContext | None = None, *, label: str = "discriminator"
) -> None:
    """A discriminator scores images (B, C, H, W) in [-1, 1] with finite logits, one set per image."""
    context = context or DEFAULT_CONTEXT
    images = _images(2, context)
    discriminator.eval()
    with torch.no_grad():
        logits = _call(label, "forward(images)", lambda: discriminator(images))
    _require(
        isinstance(logits, torch.Tensor) and logits.ndim >= 1 and logits.shape[0] == 2,
        label,
        f"logits of 2 images must be a tensor with first dimension 2, got {tuple(getattr(logits, 'shape', ()))}",
    )
    _require(bool(torch.isfinite(logits).all()), label, "logits have NaN or Inf values")


class OracleDenoiser:
    """A denoiser that always predicts the same code grid with certainty: what every sampler must
    then return exactly (used by :func:`check_sampler` and :func:`check_generator`)."""

    def __init__(self, target_BL: torch.Tensor, num_codes: int) -> None:
        self.target_BL, self.num_codes, self.calls = target_BL, num_codes, 0

    def __call__(self, codes_t_BL: torch.Tensor, t_B: torch.Tensor) -> torch.Tensor:
        self.calls += 1
        onehot_BLC = torch.nn.functional.one_hot(self.target_BL[: len(codes_t_BL)], self.num_codes + 1).float()
        return torch.log(onehot_BLC.clamp_min(1e-30)).clamp_min(-70.0).transpose(1, 2)


class _ArgmaxSampler(Sampler):
    """A one-call sampler for :func:`check_generator`: the most likely code of the all-MASK prediction."""

    def sample(
        self,
        denoise: Callable[..., torch.Tensor],
        schedule: Any,
        *,
        length: int,
        steps: int,
        generators: list[torch.Generator],
    ) -> torch.Tensor:
        batch = len(generators)
        codes_t_BL = torch.full((batch, length), schedule.num_codes, dtype=torch.long)
        t_B = torch.full((batch,), schedule.num_steps - 1, dtype=torch.long)
        return denoise(codes_t_BL, t_B)[:, : schedule.num_codes].argmax(dim=1)


def _condition_tokens(batch: int, context: BuildContext, seed: int = 0, tokens: int = 2) -> ConditionTokens:
    generator = _generator(seed)
    return ConditionTokens(
        torch.randn(batch, tokens, context.cond_dim, generator=generator), torch.zeros(batch, dtype=torch.bool)
    )


def check_generator(generator: Generator, context: BuildContext | None = None, *, label: str = "generator") -> None:
    """A generator's training loss of random code grids (codebook_size, code_grid of the context) is a
    finite scalar whose gradient reaches its parameters, batch 1 included, and under bf16 autocast;
    it samples (B, H, W) codes in [0, codebook_size) with and without guidance, and the same
    generators give the same codes."""
    context = context or DEFAULT_CONTEXT
    size, grid_hw = context.codebook_size, image_hw(context.code_grid)
    _require(
        size >= 2 and min(grid_hw) >= 1, label, "check_generator needs a context with codebook_size >= 2 and code_grid"
    )
    codes_BHW = torch.randint(size, (3, *grid_hw), generator=_generator(1))
    generator.train()
    loss, scalars = _call(
        label,
        "training_loss",
        lambda: generator.training_loss(codes_BHW, _condition_tokens(3, context), generator=_generator(2)),
    )
    _require(
        isinstance(loss, torch.Tensor) and loss.ndim == 0 and bool(torch.isfinite(loss)),
        label,
        f"training_loss must return a finite scalar tensor, got {loss!r}",
    )
    _require(
        isinstance(scalars, dict) and all(isinstance(v, float) for v in scalars.values()),
        label,
        "training_loss must return a dict of floats to log next to the loss",
    )
    loss.backward()
    trained = [(name, p) for name, p in generator.named_parameters() if p.requires_grad]
    no_grad = [name for name, p in trained if p.grad is None or not bool(torch.isfinite(p.grad).all())]
    _require(trained and len(no_grad) < len(trained), label, "the loss's gradient reaches none of the parameters")
    generator.zero_grad(set_to_none=True)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        bf16, _ = _call(
            label,
            "training_loss under bf16 autocast",
            lambda: generator.training_loss(codes_BHW[:1], _condition_tokens(1, context), generator=_generator(3)),
        )
    _require(bool(torch.isfinite(bf16)), label, "training_loss of batch 1 under bf16 autocast is not finite")
    generator.eval()
    sampler = _ArgmaxSampler()
    for guidance in (1.0, 3.0):
        draws = lambda: [_generator(10 + row) for row in range(2)]  # noqa: E731
        condition, null = _condition_tokens(2, context), _condition_tokens(2, context, seed=5)
        first = _call(
            label,
            f"sample (guidance {guidance})",
            lambda: generator.sample(condition, sampler, steps=1, null=null, guidance=guidance, generators=draws()),
        )
        again = generator.sample(condition, sampler, steps=1, null=null, guidance=guidance, generators=draws())
        _require(
            tuple(first.shape) == (2, *grid_hw) and not first.dtype.is_floating_point,
            label,
            f"sample must return integer codes (2, {grid_hw[0]}, {grid_hw[1]}), got {first.dtype} {tuple(first.shape)}",
        )
        _require(bool(((first >= 0) & (first < size)).all()), label, f"sampled codes outside [0, {size})")
        _require(torch.equal(first, again), label, "the same generators gave different codes")


def check_sampler(
    sampler: Sampler, context: BuildContext | None = None, *, schedule: Any, label: str = "sampler"
) -> None:
    """With ``schedule`` (a generator's forward process: ``num_codes``, ``num_steps``, ``mask_index``,
    ``posterior``), a sampler returns exactly the code grid an oracle denoiser predicts with
    certainty, for 1, 2 and 10 steps and a 1-token grid, without MASK; it calls the denoiser at
    most ``steps`` times, and a row's result does not depend on the other rows of its batch.
    :func:`check_plugin` takes the schedule from a registered generator (see
    :func:`schedule_from_host`)."""
    size = schedule.num_codes
    for length, steps in ((16, 1), (16, 2), (16, min(10, schedule.num_steps)), (1, 3)):
        target_BL = torch.randint(size, (3, length), generator=_generator(length + steps))
        oracle = OracleDenoiser(target_BL, size)
        codes = _call(
            label,
            f"sample ({steps} steps, {length} tokens)",
            lambda: sampler.sample(
                oracle, schedule, length=length, steps=steps, generators=[_generator(row) for row in range(3)]
            ),
        )
        _require(
            torch.equal(codes.long(), target_BL),
            label,
            f"with a certain denoiser, {steps} steps on {length} tokens must give exactly its prediction",
        )
        _require(oracle.calls <= steps, label, f"called the denoiser {oracle.calls} times for steps={steps}")
    # Row 1 alone (with its own generator) equals row 1 of a batch of 3, for an uncertain denoiser.
    logits_BCL = torch.randn(3, size + 1, 16, generator=_generator(99))
    logits_BCL[:, size] = -70.0

    def uncertain(codes_t_BL: torch.Tensor, t_B: torch.Tensor) -> torch.Tensor:
        rows = logits_BCL[: len(codes_t_BL)] if len(codes_t_BL) == 3 else logits_BCL[1:2]
        return torch.log_softmax(rows, dim=1).clamp_min(-70.0)

    batch = sampler.sample(uncertain, schedule, length=16, steps=4, generators=[_generator(20 + r) for r in range(3)])
    alone = sampler.sample(uncertain, schedule, length=16, steps=4, generators=[_generator(21)])
    _require(
        torch.equal(batch[1:2], alone),
        label,
        "a row's codes changed with the rest of its batch (draw each row's randomness from its own generator)",
    )
    _require(bool((batch < size).all()), label, "the output holds MASK tokens")


def schedule_from_host(host: PluginHost, context: BuildContext | None = None) -> Any:
    """The forward process of the first registered generator that has one (``generator.schedule``),
    built in ``context`` with its default options; None when no generator has a schedule."""
    context = context or DEFAULT_CONTEXT
    for name in host.registry("generator").names():
        try:
            generator = host.build("generator", {"name": name}, context)
        except (VqtouchError, MissingWeightsError):
            continue
        if hasattr(generator, "schedule"):
            return generator.schedule
    return None


def _check_sampler_with_host(sampler: Sampler, context: BuildContext, *, label: str, host: PluginHost) -> None:
    schedule = schedule_from_host(host, context)
    if schedule is None:
        _skip(
            f"{label}: no installed generator provides a forward process (generator.schedule) to sample from",
            VqtouchError("no generator"),
        )
    check_sampler(sampler, context, schedule=schedule, label=label)

"""Vector quantizers: ``vq`` (gradient-trained codebook) and ``ema_vq`` (EMA codebook + dead-code restart).

Both map latents (B, D, h, w) to their nearest codebook entries and integer codes (B, h, w), pass
gradients to the encoder with the straight-through estimator (or, with ``rotation_trick``, through
the rotation that takes each latent onto its code), and return the batch perplexity exp(entropy of
the code histogram).

Precision: every piece of quantizer maths (projections, normalisation, distances, losses, EMA
statistics) runs in float32 with autocast switched off, whatever the caller's autocast or input
dtype.  In half precision the distance ``||e||^2 - 2 z.e`` loses the differences between codes, and
EMA cluster sizes underflow (rosinality/vq-vae-2-pytorch #65, encodec-pytorch #8).  The quantized
latents are returned in float32; the decoder's first layer runs under the caller's autocast, which
casts them to the compute dtype it wants.  One thing autocast-off cannot switch off: if the program
enables TF32 matmuls globally (``torch.backends.cuda.matmul.fp32_precision = "tf32"``), the distance
matmul inherits it on Ampere+ GPUs (about 1e-3 relative error), so near-ties may pick a code that is
not exactly the nearest.  We do not flip that global flag here: doing it per call is not thread-safe,
and PyTorch raises when the legacy and the new TF32 APIs are mixed.
"""

from __future__ import annotations

import contextlib
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from vqtouch.core import BuildContext, ConfigError, Quantizer, QuantizerOutput

from .quantizers_plugin import CodebookInit  # noqa: F401 - re-exported: its old home
from .quantizers_plugin import EmaVectorQuantizerConfig, VectorQuantizerConfig

#: Largest (rows x codes) distance block materialised at once (~256 MB in float32).  A 16384-code
#: codebook on a batch of 64x64 latent grids would otherwise need gigabytes for one matrix.
MAX_DISTANCE_ELEMENTS = 64 * 2**20

# -- shared maths -------------------------------------------------------------------------------


def _autocast_disabled(device: torch.device) -> contextlib.AbstractContextManager:
    """Switch autocast off for ``device``'s type (a no-op context for types autocast does not know)."""
    if torch.amp.is_autocast_available(device.type):
        return torch.autocast(device_type=device.type, enabled=False)
    return contextlib.nullcontext()


def nearest_codes(vectors_NC: torch.Tensor, codebook_KC: torch.Tensor) -> torch.Tensor:
    """Index (N,) of the codebook row nearest to each row of ``vectors_NC`` in squared l2 distance.

    The distance is ||z||^2 + ||e||^2 - 2 z.e in float32, evaluated in row blocks so that no more than
    ``MAX_DISTANCE_ELEMENTS`` distances exist at once.  ||z||^2 is the same for every code of a row, so
    it cannot change the argmin and is left out: adding it would round the differences between codes
    to the float32 spacing of a large ||z||^2 (e.g. 64 for latents of magnitude 1e4) and pick wrong codes.
    """
    vectors_NC = vectors_NC.float()
    codebook_KC = codebook_KC.float()
    codebook_sq_K = codebook_KC.square().sum(dim=1)
    rows_per_block = max(1, MAX_DISTANCE_ELEMENTS // codebook_KC.shape[0])
    codes = []
    for start in range(0, vectors_NC.shape[0], rows_per_block):
        block_nC = vectors_NC[start : start + rows_per_block]
        # ||e||^2 - 2 z.e in one fused GEMM.
        scores_nK = torch.addmm(codebook_sq_K.unsqueeze(0), block_nC, codebook_KC.T, alpha=-2.0)
        codes.append(scores_nK.argmin(dim=1))
    return torch.cat(codes) if len(codes) > 1 else codes[0]


def rotate_onto(vectors_NC: torch.Tensor, codes_NC: torch.Tensor) -> torch.Tensor:
    """The rotation trick's gradient path (Fifty et al. 2024): ``lambda R z`` with ``R`` the rotation
    taking the direction of each vector ``z`` onto that of its code ``e`` and ``lambda = |e| / |z|``,
    both treated as constants, so the value is ``e`` and the encoder's gradient is ``lambda R^T g``.

    ``R z = z - 2 r (r . z) + 2 e^ (u . z)`` with ``u = z / |z|``, ``e^ = e / |e|`` and
    ``r = (u + e^) / |u + e^|`` (two Householder reflections, never a D x D matrix).  A vector of
    (near) zero length has no direction: it keeps the identity gradient.
    """
    norm_N1 = vectors_NC.detach().norm(dim=1, keepdim=True)
    code_norm_N1 = codes_NC.detach().norm(dim=1, keepdim=True)
    u_NC = vectors_NC.detach() / norm_N1.clamp_min(1e-12)
    e_hat_NC = codes_NC.detach() / code_norm_N1.clamp_min(1e-12)
    r_NC = F.normalize(u_NC + e_hat_NC, dim=1, eps=1e-12)
    rotated_NC = (
        vectors_NC
        - 2 * r_NC * (r_NC * vectors_NC).sum(dim=1, keepdim=True)
        + 2 * e_hat_NC * (u_NC * vectors_NC).sum(dim=1, keepdim=True)
    )
    scaled_NC = rotated_NC * (code_norm_N1 / norm_N1.clamp_min(1e-12))
    return torch.where(norm_N1 > 1e-6, scaled_NC, vectors_NC)


def perplexity_of_counts(counts_K: torch.Tensor, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """exp(entropy) of a code histogram: 1 when one code is used, K when K codes are used equally.

    ``dtype``: float64 for a report over a whole evaluation set (counts can exceed 2**24).
    """
    probabilities_K = counts_K.to(dtype) / counts_K.sum().clamp_min(1).to(dtype)
    entropy = -torch.special.xlogy(probabilities_K, probabilities_K).sum()  # 0 log 0 = 0
    return entropy.exp()


def check_latents(quantizer: Quantizer, latents_BDhw: torch.Tensor) -> None:
    """Refuse, in one line, latents a quantizer cannot take: not floating point, not (B, D, h, w), empty."""
    name = type(quantizer).__name__
    if not isinstance(latents_BDhw, torch.Tensor) or not latents_BDhw.dtype.is_floating_point:
        kind = latents_BDhw.dtype if isinstance(latents_BDhw, torch.Tensor) else type(latents_BDhw).__name__
        raise ValueError(f"{name} expects a floating-point latent tensor, got {kind}")
    if latents_BDhw.ndim != 4 or latents_BDhw.shape[1] != quantizer.embedding_dim:
        raise ValueError(
            f"{name} expects latents of shape (B, {quantizer.embedding_dim}, h, w), got {tuple(latents_BDhw.shape)}"
        )
    if latents_BDhw.numel() == 0:
        raise ValueError(f"{name} got an empty latent batch of shape {tuple(latents_BDhw.shape)}")


def checked_codes(quantizer: Quantizer, codes_Bhw: Any) -> torch.Tensor:
    """``codes_Bhw`` as a tensor when they are integer codes (B, h, w) in [0, codebook_size); else one line."""
    name = type(quantizer).__name__
    codes_Bhw = torch.as_tensor(codes_Bhw)
    if codes_Bhw.dtype.is_floating_point or codes_Bhw.dtype.is_complex or codes_Bhw.dtype == torch.bool:
        raise ValueError(f"{name}.lookup expects integer codes, got dtype {codes_Bhw.dtype}")
    if codes_Bhw.ndim != 3:
        raise ValueError(f"{name}.lookup expects codes of shape (B, h, w), got shape {tuple(codes_Bhw.shape)}")
    size = quantizer.codebook_size
    if codes_Bhw.numel() and (int(codes_Bhw.min()) < 0 or int(codes_Bhw.max()) >= size):
        low, high = int(codes_Bhw.min()), int(codes_Bhw.max())
        raise ValueError(f"codes must be in [0, {size}) for this codebook; got min {low}, max {high}")
    return codes_Bhw


def _init_codebook_(codebook_KC: torch.Tensor, init: str) -> None:
    size = codebook_KC.shape[0]
    if init == "uniform":
        codebook_KC.uniform_(-1.0 / size, 1.0 / size)
    else:
        codebook_KC.normal_(0.0, 1.0)


def _distributed() -> bool:
    return torch.distributed.is_available() and torch.distributed.is_initialized()


# -- quantizers ---------------------------------------------------------------------------------


class _NearestNeighbourQuantizer(Quantizer):
    """Shared lookup, straight-through, perplexity and usage bookkeeping of ``vq`` and ``ema_vq``.

    Subclasses own ``codebook_KC`` (a parameter or a buffer) and implement :meth:`_vq_loss` and,
    optionally, :meth:`_update_codebook` (called in training mode after the codes are chosen).
    Perplexity and usage counts describe this process's batch only (no collective calls), so a
    reporting call on rank 0 alone cannot deadlock under DDP.
    """

    codebook_KC: torch.Tensor

    def __init__(
        self,
        codebook_size: int,
        embedding_dim: int,
        lookup_dim: int = 0,
        l2_normalize: bool = False,
        rotation_trick: bool = False,
    ) -> None:
        super().__init__()
        self.codebook_size = codebook_size
        self.embedding_dim = embedding_dim
        self.l2_normalize = l2_normalize
        self.rotation_trick = rotation_trick
        #: Width C of the space codes are looked up in (D unless the lookup is factorised).
        self.code_dim = lookup_dim or embedding_dim
        if lookup_dim:
            self.project_in = nn.Linear(embedding_dim, lookup_dim)
            self.project_out = nn.Linear(lookup_dim, embedding_dim)
        else:
            self.project_in = self.project_out = None
        # A report accumulator, not model state: non-persistent, so checkpoints do not depend on which
        # batches were seen and a reloaded model starts a fresh report.  Under DDP it counts the codes
        # of this process only.
        self.register_buffer("usage_counts_K", torch.zeros(codebook_size, dtype=torch.long), persistent=False)

    # -- public API -------------------------------------------------------------------------------
    def forward(self, latents_BDhw: torch.Tensor) -> QuantizerOutput:
        """Quantise latents (B, D, h, w) of any float dtype; returns fp32 quantized latents and fp32 loss."""
        check_latents(self, latents_BDhw)
        batch, _, height, width = latents_BDhw.shape
        with _autocast_disabled(latents_BDhw.device):
            vectors_NC = self._to_lookup_space(latents_BDhw)
            codebook_KC = self._lookup_codebook()
            codes_N = nearest_codes(vectors_NC.detach(), codebook_KC.detach())
            selected_NC = F.embedding(codes_N, codebook_KC)
            loss = self._vq_loss(vectors_NC, selected_NC)
            # Straight-through, written so the forward value is exactly the code vector: the usual
            # z + sg(e - z) rounds e to the float32 spacing of z (1e-3 at |z| = 1e4).
            gradient_path_NC = rotate_onto(vectors_NC, selected_NC) if self.rotation_trick else vectors_NC
            straight_through_NC = selected_NC.detach() + (gradient_path_NC - gradient_path_NC.detach())
            quantized_BDhw = self._from_lookup_space(straight_through_NC, batch, height, width)
            with torch.no_grad():
                counts_K = torch.bincount(codes_N, minlength=self.codebook_size)
                perplexity = perplexity_of_counts(counts_K)
                self.usage_counts_K += counts_K
                if self.training:
                    self._update_codebook(vectors_NC.detach(), codes_N, counts_K)
        return QuantizerOutput(quantized_BDhw, codes_N.view(batch, height, width), loss, perplexity)

    def lookup(self, codes_Bhw: torch.Tensor) -> torch.Tensor:
        """Integer codes (B, h, w) in [0, K) to quantised latents (B, D, h, w) in float32."""
        codes_Bhw = checked_codes(self, codes_Bhw)
        batch, height, width = codes_Bhw.shape
        device = self.codebook_KC.device
        with _autocast_disabled(device):
            selected_NC = F.embedding(
                codes_Bhw.to(device=device, dtype=torch.long).reshape(-1), self._lookup_codebook()
            )
            return self._from_lookup_space(selected_NC, batch, height, width)

    def usage_counts(self) -> torch.Tensor:
        """(K,) how often each code was chosen since :meth:`reset_usage` (every forward call counts)."""
        return self.usage_counts_K

    def usage_fraction(self) -> float:
        """Fraction of the K codes chosen at least once since the last :meth:`reset_usage`.

        Counts every forward call, in training and in eval mode: reset before the pass you report on.
        """
        return float((self.usage_counts_K > 0).float().mean())

    def reset_usage(self) -> None:
        """Forget the usage counted so far (start of an epoch or of an evaluation pass)."""
        self.usage_counts_K.zero_()

    def extra_repr(self) -> str:
        return (
            f"codebook_size={self.codebook_size}, embedding_dim={self.embedding_dim}, "
            f"code_dim={self.code_dim}, l2_normalize={self.l2_normalize}, rotation_trick={self.rotation_trick}"
        )

    # -- subclass hooks -------------------------------------------------------------------------------
    def _vq_loss(self, vectors_NC: torch.Tensor, selected_NC: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def _update_codebook(self, vectors_NC: torch.Tensor, codes_N: torch.Tensor, counts_K: torch.Tensor) -> None:
        """Training-mode codebook update after the assignment (no-op for gradient-trained codebooks)."""

    # -- helpers ------------------------------------------------------------------------------------
    def _to_lookup_space(self, latents_BDhw: torch.Tensor) -> torch.Tensor:
        """(B, D, h, w) latents to (B*h*w, C) float32 vectors in the space codes live in."""
        vectors_NC = latents_BDhw.float().permute(0, 2, 3, 1).reshape(-1, self.embedding_dim)
        if self.project_in is not None:
            vectors_NC = F.linear(vectors_NC, self.project_in.weight.float(), self.project_in.bias.float())
        if self.l2_normalize:
            vectors_NC = F.normalize(vectors_NC, dim=1)
        return vectors_NC

    def _codebook(self) -> torch.Tensor:
        """The (K, C) float32 codebook (a subclass may compute it, e.g. SimVQ's map of a frozen basis)."""
        return self.codebook_KC.float()

    def _lookup_codebook(self) -> torch.Tensor:
        """The (K, C) float32 codebook as used for lookup (unit rows under ``l2_normalize``)."""
        codebook_KC = self._codebook()
        return F.normalize(codebook_KC, dim=1) if self.l2_normalize else codebook_KC

    def _from_lookup_space(self, vectors_NC: torch.Tensor, batch: int, height: int, width: int) -> torch.Tensor:
        """(B*h*w, C) vectors back to contiguous (B, D, h, w) float32 latents."""
        if self.project_out is not None:
            vectors_NC = F.linear(vectors_NC, self.project_out.weight.float(), self.project_out.bias.float())
        return vectors_NC.view(batch, height, width, self.embedding_dim).permute(0, 3, 1, 2).contiguous()


class VectorQuantizer(_NearestNeighbourQuantizer):
    """Nearest-neighbour vector quantizer (VQ-VAE / VQGAN) with a gradient-trained codebook.

    Loss (the correct, non-swapped form): L = ||sg[z] - e||^2 + beta * ||z - sg[e]||^2, each term a mean
    over elements, computed in the lookup space.  The straight-through output has d(out)/d(z) = I
    without ``lookup_dim``; with it, gradients pass through both projections.
    """

    def __init__(
        self,
        codebook_size: int,
        embedding_dim: int,
        beta: float = 0.25,
        lookup_dim: int = 0,
        l2_normalize: bool = False,
        init: str = "uniform",
        rotation_trick: bool = False,
        simvq: bool = False,
    ) -> None:
        super().__init__(codebook_size, embedding_dim, lookup_dim, l2_normalize, rotation_trick)
        self.beta = beta
        codebook_KC = torch.empty(codebook_size, self.code_dim, dtype=torch.float32)
        _init_codebook_(codebook_KC, init)
        if simvq:
            self.register_buffer("codebook_KC", codebook_KC)  # the frozen basis
            self.codebook_map = nn.Linear(self.code_dim, self.code_dim, bias=False)
            nn.init.eye_(self.codebook_map.weight)
        else:
            self.codebook_KC = nn.Parameter(codebook_KC)
            self.codebook_map = None

    def _codebook(self) -> torch.Tensor:
        if self.codebook_map is None:
            return self.codebook_KC.float()
        return F.linear(self.codebook_KC.float(), self.codebook_map.weight.float())

    def _vq_loss(self, vectors_NC: torch.Tensor, selected_NC: torch.Tensor) -> torch.Tensor:
        # taming's VectorQuantizer2 defaults to legacy=True, which weights these two terms the other way
        # round (commitment 1, codebook beta; taming issues #46/#57, PR #58) and its released checkpoints
        # were trained that way.  We implement only the paper's form: the codebook moves with weight 1,
        # the encoder is pulled towards its code with weight beta.
        codebook_term = F.mse_loss(selected_NC, vectors_NC.detach())
        commitment_term = F.mse_loss(vectors_NC, selected_NC.detach())
        return codebook_term + self.beta * commitment_term


class EmaVectorQuantizer(_NearestNeighbourQuantizer):
    """Vector quantizer whose codebook is an exponential moving average of the latents assigned to it.

    Training-mode forward passes update, with ``decay`` d and per-batch assignment counts n_k and
    latent sums s_k: N_k <- d N_k + (1-d) n_k, S_k <- d S_k + (1-d) s_k, e_k = S_k / N~_k with the
    Laplace-smoothed N~_k = (N_k + eps) / (sum N + K eps) * sum N (VQ-VAE appendix, sonnet).  The quantized
    output and the loss use the codebook from before the update.  The loss is the commitment term
    beta * ||z - sg[e]||^2 only; the codebook is a buffer and receives no gradient.

    Dead codes: after the update, codes with N_k < dead_threshold * (1 - d) — fewer than
    ``dead_threshold`` assignments over the ~1/(1-d) batches the EMA remembers — are moved onto random
    latents of the current batch (drawn without replacement when the batch has enough) and given
    N_k = dead_threshold * (1 - d), so one assignment in the next batch keeps them alive.  Codes start
    with the pseudo-count of a single assignment, so codes unused in the first training batch are
    replaced by data at once.  Measuring over the EMA window rather than per batch keeps the threshold
    meaningful for small batches, where K often exceeds the number of latents in a batch.

    Distributed data parallel: when ``torch.distributed`` is initialised, the batch counts and sums are
    all-reduced (sum) before the update, so every rank holds identical statistics computed from the
    global batch; the dead-code set is therefore the same on every rank, and the replacement latents
    are broadcast from rank 0 so every rank restarts them at the same vectors.  Restarting costs one
    host synchronisation per training step (to know how many codes are dead).
    """

    def __init__(
        self,
        codebook_size: int,
        embedding_dim: int,
        beta: float = 0.25,
        decay: float = 0.99,
        eps: float = 1e-5,
        dead_threshold: float = 2.0,
        init: str = "uniform",
        rotation_trick: bool = False,
    ) -> None:
        super().__init__(codebook_size, embedding_dim, rotation_trick=rotation_trick)
        self.beta = beta
        self.decay = decay
        self.eps = eps
        self.dead_threshold = dead_threshold
        codebook_KC = torch.empty(codebook_size, embedding_dim, dtype=torch.float32)
        _init_codebook_(codebook_KC, init)
        initial_count = 1.0 - decay  # the EMA weight of one assignment
        # EMA statistics are float32 buffers: persistent, so training resumes exactly from a checkpoint.
        self.register_buffer("codebook_KC", codebook_KC)
        self.register_buffer("ema_cluster_size_K", torch.full((codebook_size,), initial_count))
        self.register_buffer("ema_embedding_sum_KC", codebook_KC * initial_count)

    @property
    def dead_count_threshold(self) -> float:
        """The EMA cluster size below which a code counts as dead: dead_threshold * (1 - decay)."""
        return self.dead_threshold * (1.0 - self.decay)

    def _vq_loss(self, vectors_NC: torch.Tensor, selected_NC: torch.Tensor) -> torch.Tensor:
        return self.beta * F.mse_loss(vectors_NC, selected_NC.detach())

    def _update_codebook(self, vectors_NC: torch.Tensor, codes_N: torch.Tensor, counts_K: torch.Tensor) -> None:
        batch_counts_K = counts_K.float()
        batch_sums_KC = torch.zeros_like(self.ema_embedding_sum_KC, dtype=torch.float32)
        batch_sums_KC.index_add_(0, codes_N, vectors_NC)
        if _distributed():
            torch.distributed.all_reduce(batch_counts_K)
            torch.distributed.all_reduce(batch_sums_KC)
        cluster_size_K = self.ema_cluster_size_K.float().lerp(batch_counts_K, 1.0 - self.decay)
        embedding_sum_KC = self.ema_embedding_sum_KC.float().lerp(batch_sums_KC, 1.0 - self.decay)
        total = cluster_size_K.sum()
        smoothed_K = (cluster_size_K + self.eps) / (total + self.codebook_size * self.eps) * total
        self.ema_cluster_size_K.copy_(cluster_size_K)
        self.ema_embedding_sum_KC.copy_(embedding_sum_KC)
        self.codebook_KC.copy_(embedding_sum_KC / smoothed_K.unsqueeze(1))
        if self.dead_threshold > 0:
            self._restart_dead_codes(vectors_NC)

    def _restart_dead_codes(self, vectors_NC: torch.Tensor) -> None:
        threshold = self.dead_count_threshold
        dead_K = self.ema_cluster_size_K < threshold
        num_dead = int(dead_K.sum())  # host sync; identical on every rank (the statistics are all-reduced)
        if num_dead == 0:
            return
        dead_codes = dead_K.nonzero().squeeze(1)
        num_vectors = vectors_NC.shape[0]
        if num_vectors >= num_dead:
            picks = torch.randperm(num_vectors, device=vectors_NC.device)[:num_dead]
        else:  # more dead codes than latents: duplicates are harmless, the spares restart next step
            picks = torch.randint(num_vectors, (num_dead,), device=vectors_NC.device)
        replacements_nC = vectors_NC[picks].float().contiguous()
        if _distributed():
            torch.distributed.broadcast(replacements_nC, src=0)
        self.codebook_KC[dead_codes] = replacements_nC.to(self.codebook_KC.dtype)
        self.ema_cluster_size_K[dead_codes] = threshold
        self.ema_embedding_sum_KC[dead_codes] = (replacements_nC * threshold).to(self.ema_embedding_sum_KC.dtype)


# -- factories ----------------------------------------------------------------------------------


def _resolve_sizes(plugin: str, config: VectorQuantizerConfig | EmaVectorQuantizerConfig, context: BuildContext) -> int:
    """The embedding width from the config or the context; ConfigError when unknown or contradictory."""
    embedding_dim = config.embedding_dim or context.latent_dim
    if embedding_dim < 1:
        raise ConfigError(
            f"quantizer {plugin!r} needs the latent width: set quantizer.embedding_dim=N or build "
            "it with the encoder's latent width in the context (BuildContext.latent_dim)"
        )
    if config.embedding_dim and context.latent_dim and config.embedding_dim != context.latent_dim:
        raise ConfigError(
            f"quantizer {plugin!r}: embedding_dim={config.embedding_dim} but the encoder's latents "
            f"have {context.latent_dim} channels; set embedding_dim=0 to follow the encoder"
        )
    if context.codebook_size and context.codebook_size != config.codebook_size:
        raise ConfigError(
            f"quantizer {plugin!r}: codebook_size={config.codebook_size} but the experiment expects "
            f"{context.codebook_size} codes (BuildContext.codebook_size); make them agree"
        )
    return embedding_dim


def build_vector_quantizer(config: VectorQuantizerConfig, context: BuildContext) -> VectorQuantizer:
    """Factory of ``vq``: the latent width comes from the config, else from the encoder via the context."""
    embedding_dim = _resolve_sizes("vq", config, context)
    return VectorQuantizer(
        config.codebook_size,
        embedding_dim,
        beta=config.beta,
        lookup_dim=config.lookup_dim,
        l2_normalize=config.l2_normalize,
        init=config.init,
        rotation_trick=config.rotation_trick,
        simvq=config.simvq,
    )


def build_ema_vector_quantizer(config: EmaVectorQuantizerConfig, context: BuildContext) -> EmaVectorQuantizer:
    """Factory of ``ema_vq``: the latent width comes from the config, else from the encoder via the context."""
    embedding_dim = _resolve_sizes("ema_vq", config, context)
    return EmaVectorQuantizer(
        config.codebook_size,
        embedding_dim,
        beta=config.beta,
        decay=config.decay,
        eps=config.eps,
        dead_threshold=config.dead_threshold,
        init=config.init,
        rotation_trick=config.rotation_trick,
    )

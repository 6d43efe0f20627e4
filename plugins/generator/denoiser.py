"""The x_0-predicting network of the discrete-diffusion decoder (VQ-Diffusion's ``selfcross`` transformer).

Input: codes (B, L) in [0, K] (K = MASK) on an H x W grid (row-major, L = H W), timesteps (B,) in
[0, T-1] and condition tokens (B, M, cond_dim).  Output: logits (B, K, L) over the K code classes,
never MASK; :func:`vqtouch.plugins.generator.diffusion.log_predict_x0` turns them into the x_0
distribution the diffusion maths works with.

Each block: adaptive LayerNorm (timestep) -> self-attention; adaptive LayerNorm -> cross-attention to
the condition tokens; adaptive LayerNorm -> MLP; every sub-layer residual.

Besides cross-attention the condition reaches the network two more ways (both zero-initialised, so
they start as no-ops and a checkpoint saved without them loads and computes exactly as before):

- globally: the mean of the projected condition tokens is added to the timestep embedding that
  drives every adaptive LayerNorm (VQ-Diffusion's class-AdaLN, for any conditioner);
- spatially: a condition image aligned with the target (``grid_BDhw`` of the condition, see
  :class:`vqtouch.core.ConditionTokens`) is resized to the code grid, L2-normalised per position,
  projected and added to the token embeddings, so a code sees the condition at its own place.

Attention goes through :func:`attend`.  LayerNorms run in float32 and the residual stream stays
float32 under autocast, so bf16 autocast only lowers the matmuls (outputs stay finite, logits are
float32).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from vqtouch.core import load_missing_as_zeros


@dataclass
class ConditionCache:
    """The condition tokens of one batch, encoded once for every block (see
    :meth:`DiffusionTransformer.precompute_condition`), so a sampler reuses them across its steps."""

    #: Per block, cross-attention keys and values, each (B, heads, M, width / heads).
    keys_values: list[tuple[torch.Tensor, torch.Tensor]]
    #: Boolean attention mask (B, 1, 1, M), True where a token is attended; None when all are.
    attn_mask_B11M: torch.Tensor | None
    #: (B,) False for rows without any valid token, whose cross-attention then adds nothing; None
    #: when every row has one.
    has_tokens_B: torch.Tensor | None
    #: The condition's global embedding (B, width), added to the timestep embedding.
    global_Bd: torch.Tensor | None = None
    #: The aligned condition image's embedding at each code (B, L, width); None without a grid.
    grid_BLd: torch.Tensor | None = None

    @property
    def batch_size(self) -> int:
        """Number of rows B the cache was computed for."""
        return self.keys_values[0][0].shape[0]


def _layer_norm(
    x_BLd: torch.Tensor, weight: torch.Tensor | None = None, bias: torch.Tensor | None = None
) -> torch.Tensor:
    """LayerNorm in float32 whatever the autocast: bf16 statistics of a float32 residual lose the
    small differences between tokens."""
    return F.layer_norm(
        x_BLd.float(),
        x_BLd.shape[-1:],
        None if weight is None else weight.float(),
        None if bias is None else bias.float(),
        eps=1e-6,
    )


#: The most attention scores (batch x heads x queries x keys) :func:`attend` materialises: 64 Mi, 128 MB
#: in bf16 per layer (kept with its softmax for the backward).
EXPLICIT_ATTENTION_MAX_SCORES = 2**26


def attend(
    q_BhLc: torch.Tensor,
    k_BhMc: torch.Tensor,
    v_BhMc: torch.Tensor,
    attn_mask_B11M: torch.Tensor | None = None,
    dropout: float = 0.0,
) -> torch.Tensor:
    """Softmax attention, (B, heads, L, c), with ``mask`` True where a key may be attended.

    ``F.scaled_dot_product_attention`` everywhere but one case: bf16 with gradients on the CPU,
    where its fused kernel's backward runs slower than fp32's (bench/bench_precision.py: the ``tour``
    generator's training step 1.16x fp32 with it, 1.6x with the explicit form).  The explicit form
    is the same arithmetic (bf16 products, the softmax computed in fp32 and rounded to bf16 before
    the product with the values, as the fused kernels do) as two AMX matrix products.  It keeps the
    (B, heads, L, M) scores for the backward, so above :data:`EXPLICIT_ATTENTION_MAX_SCORES` of them
    (a 32 x 32 code grid at batch 16 and 8 heads) the fused kernel, whose memory grows with L, runs.
    """
    batch, heads, length, _ = q_BhLc.shape
    explicit = q_BhLc.dtype == torch.bfloat16 and q_BhLc.device.type == "cpu" and torch.is_grad_enabled()
    if not explicit or batch * heads * length * k_BhMc.shape[2] > EXPLICIT_ATTENTION_MAX_SCORES:
        return F.scaled_dot_product_attention(q_BhLc, k_BhMc, v_BhMc, attn_mask=attn_mask_B11M, dropout_p=dropout)
    scores_BhLM = (q_BhLc * q_BhLc.shape[-1] ** -0.5) @ k_BhMc.transpose(-1, -2)
    if attn_mask_B11M is not None:
        scores_BhLM = scores_BhLM.masked_fill(~attn_mask_B11M, float("-inf"))
    weights_BhLM = scores_BhLM.softmax(dim=-1)
    if dropout:
        weights_BhLM = F.dropout(weights_BhLM, dropout)
    return weights_BhLM @ v_BhMc


class _SelfAttention(nn.Module):
    def __init__(self, width: int, heads: int, dropout: float) -> None:
        super().__init__()
        self.heads = heads
        self.dropout = dropout
        self.qkv = nn.Linear(width, 3 * width)
        self.proj = nn.Linear(width, width)

    def forward(self, h_BLd: torch.Tensor) -> torch.Tensor:
        batch, length, width = h_BLd.shape
        q, k, v = self.qkv(h_BLd).view(batch, length, 3, self.heads, width // self.heads).permute(2, 0, 3, 1, 4)
        out_BhLc = attend(q, k, v, dropout=self.dropout if self.training else 0.0)
        return self.proj(out_BhLc.transpose(1, 2).reshape(batch, length, width))


class _CrossAttention(nn.Module):
    def __init__(self, width: int, heads: int, dropout: float) -> None:
        super().__init__()
        self.heads = heads
        self.dropout = dropout
        self.q = nn.Linear(width, width)
        self.kv = nn.Linear(width, 2 * width)
        self.proj = nn.Linear(width, width)

    def keys_values(self, cond_BMd: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Keys and values (B, heads, M, c) of the projected condition tokens."""
        batch, tokens, width = cond_BMd.shape
        k, v = self.kv(cond_BMd).view(batch, tokens, 2, self.heads, width // self.heads).permute(2, 0, 3, 1, 4)
        return k, v

    def forward(
        self,
        h_BLd: torch.Tensor,
        keys_values: tuple[torch.Tensor, torch.Tensor],
        attn_mask_B11M: torch.Tensor | None,
        has_tokens_B: torch.Tensor | None,
    ) -> torch.Tensor:
        batch, length, width = h_BLd.shape
        q = self.q(h_BLd).view(batch, length, self.heads, width // self.heads).transpose(1, 2)
        # A cache made outside autocast may meet queries made inside it (or the reverse).
        k, v = (tensor.to(q.dtype) for tensor in keys_values)
        out_BhLc = attend(q, k, v, attn_mask_B11M, dropout=self.dropout if self.training else 0.0)
        out_BLd = self.proj(out_BhLc.transpose(1, 2).reshape(batch, length, width))
        if has_tokens_B is not None:
            out_BLd = out_BLd * has_tokens_B.view(-1, 1, 1).to(out_BLd.dtype)
        return out_BLd


class _Block(nn.Module):
    """Self-attention, cross-attention and MLP, each behind a timestep-adaptive LayerNorm."""

    def __init__(
        self, width: int, heads: int, mlp_ratio: float, dropout: float, grid_hw: tuple[int, int], mlp_conv: int = 0
    ) -> None:
        super().__init__()
        self.grid_hw = grid_hw
        # shift and scale of the three adaptive LayerNorms, from the block's view of the timestep.
        self.modulation = nn.Linear(width, 6 * width)
        self.self_attn = _SelfAttention(width, heads, dropout)
        self.cross_attn = _CrossAttention(width, heads, dropout)
        hidden = max(1, round(width * mlp_ratio))
        self.mlp = nn.Sequential(nn.Linear(width, hidden), nn.GELU(), nn.Linear(hidden, width), nn.Dropout(dropout))
        # A depthwise convolution over the code grid between the MLP's layers: every code mixes its
        # neighbours' features with weights shared across positions, a locality prior attention must
        # otherwise learn.  Zero-initialised and residual, so it starts as the plain MLP.
        self.mlp_conv = nn.Conv2d(hidden, hidden, mlp_conv, padding=mlp_conv // 2, groups=hidden) if mlp_conv else None
        if self.mlp_conv is not None:
            nn.init.zeros_(self.mlp_conv.weight)
            nn.init.zeros_(self.mlp_conv.bias)
        self.drop = nn.Dropout(dropout)

    def _mlp(self, h_BLd: torch.Tensor) -> torch.Tensor:
        if self.mlp_conv is None:
            return self.mlp(h_BLd)
        hidden_BLc = self.mlp[1](self.mlp[0](h_BLd))
        batch, length, channels = hidden_BLc.shape
        hidden_BcHW = hidden_BLc.transpose(1, 2).reshape(batch, channels, *self.grid_hw)
        hidden_BLc = hidden_BLc + self.mlp_conv(hidden_BcHW).flatten(2).transpose(1, 2)
        return self.mlp[3](self.mlp[2](hidden_BLc))

    def forward(
        self,
        x_BLd: torch.Tensor,
        time_Bd: torch.Tensor,
        keys_values: tuple[torch.Tensor, torch.Tensor],
        attn_mask_B11M: torch.Tensor | None,
        has_tokens_B: torch.Tensor | None,
    ) -> torch.Tensor:
        modulation = self.modulation(time_Bd).float().unsqueeze(1).chunk(6, dim=-1)

        def adaptive_norm(x: torch.Tensor, index: int) -> torch.Tensor:
            shift, scale = modulation[2 * index], modulation[2 * index + 1]
            return _layer_norm(x) * (1.0 + scale) + shift

        x_BLd = x_BLd + self.drop(self.self_attn(adaptive_norm(x_BLd, 0))).float()
        x_BLd = (
            x_BLd
            + self.drop(self.cross_attn(adaptive_norm(x_BLd, 1), keys_values, attn_mask_B11M, has_tokens_B)).float()
        )
        return x_BLd + self._mlp(adaptive_norm(x_BLd, 2)).float()


class DiffusionTransformer(nn.Module):
    """Predicts x_0 logits (B, K, L) from noised codes, the timestep and condition tokens.

    Args:
        num_codes: codebook size K; inputs are codes in [0, K] with K = MASK.
        num_steps: diffusion steps T; the timestep table has T rows, so t must lie in [0, T-1].
        grid_hw: (H, W) of the code grid; sequences are the row-major grid, L = H * W.
        cond_dim: width of the condition tokens (``BuildContext.cond_dim``).
        depth: number of blocks.
        width: model width d (divisible by ``heads``).
        heads: attention heads of the self- and cross-attention.
        mlp_ratio: hidden width of the MLP as a multiple of d.
        dropout: dropout on attention weights and residual branches in training mode.

    The condition tokens are L2-normalised one by one (as VQ-Diffusion does with CLIP tokens: their
    scale then cannot differ between conditioners), projected to d by one shared Linear, and every
    block derives its own keys and values from that projection.
    """

    def __init__(
        self,
        num_codes: int,
        num_steps: int,
        grid_hw: tuple[int, int],
        cond_dim: int,
        depth: int = 8,
        width: int = 256,
        heads: int = 8,
        mlp_ratio: float = 4.0,
        dropout: float = 0.0,
        mlp_conv: int = 0,
    ) -> None:
        super().__init__()
        height, grid_width = grid_hw
        for name, value in (
            ("num_codes", num_codes),
            ("num_steps", num_steps),
            ("grid height", height),
            ("grid width", grid_width),
            ("cond_dim", cond_dim),
            ("depth", depth),
            ("width", width),
            ("heads", heads),
        ):
            if value < 1:
                raise ValueError(f"DiffusionTransformer: {name} must be >= 1; got {value}")
        if width % heads:
            raise ValueError(f"DiffusionTransformer: width {width} is not divisible by heads {heads}")
        if not 0.0 <= dropout < 1.0:
            raise ValueError(f"DiffusionTransformer: dropout must lie in [0, 1); got {dropout}")
        if mlp_conv < 0 or (mlp_conv and mlp_conv % 2 == 0):
            raise ValueError(f"DiffusionTransformer: mlp_conv must be 0 (off) or an odd kernel size; got {mlp_conv}")
        #: Codebook size K (MASK = K).
        self.num_codes = num_codes
        #: Number of timesteps T.
        self.num_steps = num_steps
        #: (H, W) of the code grid.
        self.grid_hw = (height, grid_width)
        self.cond_dim = cond_dim
        self.width = width
        self.token_embed = nn.Embedding(num_codes + 1, width)
        self.row_embed = nn.Embedding(height, width)
        self.col_embed = nn.Embedding(grid_width, width)
        self.time_embed = nn.Embedding(num_steps, width)
        self.cond_proj = nn.Linear(cond_dim, width)
        self.cond_global = nn.Linear(width, width)
        self.grid_proj = nn.Linear(cond_dim, width)
        self.blocks = nn.ModuleList(
            _Block(width, heads, mlp_ratio, dropout, (height, grid_width), mlp_conv) for _ in range(depth)
        )
        self.head_norm = nn.LayerNorm(width, eps=1e-6)
        self.head = nn.Linear(width, num_codes)
        self.apply(self._init_weights)
        for layer in (self.cond_global, self.grid_proj):
            nn.init.zeros_(layer.weight)
        # Checkpoints saved before these paths existed load them as zeros: the no-ops they replace.
        load_missing_as_zeros(self, "cond_global", "grid_proj")

    @staticmethod
    def _init_weights(module: nn.Module) -> None:
        # GPT-style N(0, 0.02).  Nothing is zero-initialised: a zero head or modulation would leave
        # the timestep embedding without gradient at the first step.
        if isinstance(module, (nn.Linear, nn.Embedding)):
            nn.init.normal_(module.weight, std=0.02)
        if isinstance(module, nn.Linear) and module.bias is not None:
            nn.init.zeros_(module.bias)

    def precompute_condition(
        self, cond_BMD: torch.Tensor, mask: torch.Tensor | None = None, grid_BDhw: torch.Tensor | None = None
    ) -> ConditionCache:
        """Encode condition tokens (B, M, cond_dim), and the aligned condition grid (B, cond_dim, h, w)
        when there is one, once for every block.

        ``mask`` (B, M) bool: True where a token is real, False where it is padding (the convention
        of ``scaled_dot_product_attention``, the opposite of ``nn.MultiheadAttention``'s
        key_padding_mask).  A row with no real token gets no cross-attention contribution.
        """
        if cond_BMD.ndim != 3 or cond_BMD.shape[-1] != self.cond_dim:
            raise ValueError(f"expected condition tokens (B, M, {self.cond_dim}); got {tuple(cond_BMD.shape)}")
        # Normalise in float32: a bf16 sum of squares over cond_dim entries loses digits.
        cond_BMd = self.cond_proj(F.normalize(cond_BMD.float(), dim=-1))
        keys_values = [block.cross_attn.keys_values(cond_BMd) for block in self.blocks]
        attn_mask_B11M = has_tokens_B = None
        if mask is not None:
            if mask.shape != cond_BMD.shape[:2]:
                raise ValueError(
                    f"condition mask must be (B, M) = {tuple(cond_BMD.shape[:2])}; got {tuple(mask.shape)}"
                )
            mask = mask.to(device=cond_BMD.device, dtype=torch.bool)
            has_tokens_B = mask.any(dim=1)
            # An all-False row would make softmax NaN; let it attend everywhere and zero its output.
            attn_mask_B11M = (mask | ~has_tokens_B.unsqueeze(1)).view(mask.shape[0], 1, 1, mask.shape[1])
        if mask is None:
            pooled_Bd = cond_BMd.float().mean(dim=1)
        else:
            weight_BM1 = mask.unsqueeze(-1).float()
            pooled_Bd = (cond_BMd.float() * weight_BM1).sum(1) / weight_BM1.sum(1).clamp_min(1.0)
        global_Bd = self.cond_global(pooled_Bd.to(cond_BMd.dtype))
        return ConditionCache(keys_values, attn_mask_B11M, has_tokens_B, global_Bd, self.grid_embedding(grid_BDhw))

    def grid_embedding(self, grid_BDhw: torch.Tensor | None) -> torch.Tensor | None:
        """The aligned condition grid on the code grid, (B, L, width), or None."""
        if grid_BDhw is None:
            return None
        if grid_BDhw.ndim != 4 or grid_BDhw.shape[1] != self.cond_dim:
            raise ValueError(f"expected a condition grid (B, {self.cond_dim}, h, w); got {tuple(grid_BDhw.shape)}")
        grid_BDhw = grid_BDhw.float()
        if tuple(grid_BDhw.shape[-2:]) != self.grid_hw:
            larger = grid_BDhw.shape[-2] >= self.grid_hw[0] and grid_BDhw.shape[-1] >= self.grid_hw[1]
            # Area averaging when shrinking (every condition pixel counts), bilinear when enlarging.
            grid_BDhw = (
                F.interpolate(grid_BDhw, size=self.grid_hw, mode="area")
                if larger
                else F.interpolate(grid_BDhw, size=self.grid_hw, mode="bilinear", align_corners=False)
            )
        # Per-position L2 normalisation, as for the tokens; a null row's zeros stay zeros.
        cells_BLD = F.normalize(grid_BDhw.flatten(2).transpose(1, 2), dim=-1, eps=1e-6)
        return self.grid_proj(cells_BLD)

    def forward(
        self,
        codes_BL: torch.Tensor,
        t_B: torch.Tensor,
        condition: torch.Tensor | None = None,
        cache: ConditionCache | None = None,
        condition_mask: torch.Tensor | None = None,
        condition_grid: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """x_0 logits (B, K, L) in float32 for codes (B, L) in [0, K] at timesteps (B,) in [0, T-1].

        Give either ``condition`` (B, M, cond_dim), with its optional ``condition_mask`` (B, M) and
        ``condition_grid`` (B, cond_dim, h, w), or a ``cache`` from :meth:`precompute_condition`
        (same result, without re-encoding).
        """
        if (condition is None) == (cache is None):
            raise ValueError("DiffusionTransformer.forward needs exactly one of condition and cache")
        if cache is None:
            cache = self.precompute_condition(condition, condition_mask, condition_grid)
        elif condition_mask is not None or condition_grid is not None:
            raise ValueError("condition_mask and condition_grid belong to precompute_condition when a cache is passed")
        height, grid_width = self.grid_hw
        if codes_BL.ndim != 2 or codes_BL.shape[1] != height * grid_width:
            raise ValueError(
                f"expected codes (B, {height * grid_width}) on the {height}x{grid_width} grid; "
                f"got {tuple(codes_BL.shape)}"
            )
        if t_B.shape != (codes_BL.shape[0],):
            raise ValueError(f"expected timesteps ({codes_BL.shape[0]},); got {tuple(t_B.shape)}")
        if cache.batch_size != codes_BL.shape[0]:
            raise ValueError(f"condition batch {cache.batch_size} != codes batch {codes_BL.shape[0]}")
        positions_Ld = (self.row_embed.weight.unsqueeze(1) + self.col_embed.weight.unsqueeze(0)).reshape(-1, self.width)
        x_BLd = (self.token_embed(codes_BL.long()) + positions_Ld).float()
        if cache.grid_BLd is not None:
            x_BLd = x_BLd + cache.grid_BLd.float()
        time_Bd = self.time_embed(t_B.long())
        if cache.global_Bd is not None:
            time_Bd = time_Bd + cache.global_Bd.to(time_Bd.dtype)
        time_Bd = F.silu(time_Bd)
        for block, keys_values in zip(self.blocks, cache.keys_values, strict=True):
            x_BLd = block(x_BLd, time_Bd, keys_values, cache.attn_mask_B11M, cache.has_tokens_B)
        logits_BLK = self.head(_layer_norm(x_BLd, self.head_norm.weight, self.head_norm.bias))
        return logits_BLK.float().transpose(1, 2)

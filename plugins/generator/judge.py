"""A judge for best of K: a small classifier of code grids, fitted on the run's own training codes.

Best of K (:mod:`.best_of`) keeps, of K candidates for a label, the one a score prefers.  The
generator's own class posterior is a weak judge (it names the class of real held-out codes about
half the time; docs/generation.md).  A discriminative classifier of code grids is a far
better one at little cost: fitted in about a minute on the training split the generator learned
from, it names the class of held-out real codes about 3 times in 4.

Why codes, and why the tokenizer's codebook: the candidates are code grids, so the judge reads them
before decoding and never sees an image (the evaluation's classifier reads decoded images).  Its
code embeddings are the tokenizer's own codebook vectors, frozen (L2-normalised, scaled by the square
root of their dimension), so codes that decode alike look alike from the start; with learned
embeddings on 900 grids the same network names held-out codes about 4 times in 10.

The fit is seeded and deterministic on a given machine; the ``judge`` ranker (:class:`JudgeRanker`)
fits one per loaded run (:func:`fit_run_judge`) when a pipeline first ranks with it.
"""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from vqtouch.core import ConfigError
from vqtouch.core.components import BestOfBatch, BestOfRanker

#: Epochs of the judge's fit (chosen on a validation split of the training scenes, not on held-out ones).
JUDGE_EPOCHS = 60
#: Share of cells a training grid may have replaced by random codes (each grid draws a share up to it):
#: a sample is not a clean grid.
JUDGE_NOISE = 0.1


class CodeJudge(nn.Module):
    """Names the class of a code grid (B, H, W): frozen codebook embeddings, three 3x3 convolutions (the
    second halves the grid), global average pooling, a linear layer to ``num_classes`` logits."""

    def __init__(self, codebook_KD: torch.Tensor, num_classes: int, width: int = 64) -> None:
        super().__init__()
        if codebook_KD.ndim != 2 or len(codebook_KD) < 2:
            raise ValueError(f"CodeJudge: the codebook must be (K >= 2, D); got {tuple(codebook_KD.shape)}")
        if num_classes < 2:
            raise ValueError(f"CodeJudge: a judge needs at least 2 classes; got {num_classes}")
        dim = codebook_KD.shape[1]
        self.embed = nn.Embedding.from_pretrained(F.normalize(codebook_KD.float(), dim=1) * dim**0.5)
        self.net = nn.Sequential(
            nn.Conv2d(dim, width, 3, padding=1),
            nn.GELU(),
            nn.Conv2d(width, 2 * width, 3, stride=2, padding=1),
            nn.GELU(),
            nn.Conv2d(2 * width, 2 * width, 3, padding=1),
            nn.GELU(),
            nn.AdaptiveAvgPool2d(1),
            nn.Flatten(),
            nn.Dropout(0.2),
            nn.Linear(2 * width, num_classes),
        )

    def forward(self, codes_BHW: torch.Tensor) -> torch.Tensor:
        """Class logits (B, num_classes) of integer codes (B, H, W) in [0, K)."""
        if codes_BHW.ndim != 3:
            raise ValueError(f"CodeJudge expects codes (B, H, W); got {tuple(codes_BHW.shape)}")
        return self.net(self.embed(codes_BHW.long()).permute(0, 3, 1, 2)).float()

    @torch.no_grad()
    def rank(self, codes_BHW: torch.Tensor, labels_B: torch.Tensor) -> torch.Tensor:
        """(B,) log p(label | codes) of each row's own label: best of K keeps the candidate where it is highest."""
        self.eval()
        log_p_BC = self(codes_BHW).log_softmax(1)
        labels_B = torch.as_tensor(labels_B, device=log_p_BC.device).long().view(-1)
        return log_p_BC[torch.arange(len(labels_B), device=log_p_BC.device), labels_B]


def fit_code_judge(
    codes_NHW: torch.Tensor,
    labels_N: torch.Tensor,
    codebook_KD: torch.Tensor,
    num_classes: int,
    *,
    epochs: int = JUDGE_EPOCHS,
    noise: float = JUDGE_NOISE,
    seed: int = 0,
    batch_size: int = 64,
    judge: nn.Module | None = None,
) -> nn.Module:
    """A :class:`CodeJudge` fitted by AdamW (lr 2e-3, weight decay 0.05) on ``codes_NHW`` and their
    ``labels_N`` for ``epochs`` passes; every pass replaces a random share, up to ``noise``, of each
    grid's cells by random codes.  Returned in eval mode, on the codes' device.  ``judge``: fit this
    model (codes (B, H, W) to logits) instead of a new ``CodeJudge`` (an ablation's variant)."""
    codes_NHW = torch.as_tensor(codes_NHW)
    labels_N = torch.as_tensor(labels_N).long().view(-1)
    if codes_NHW.ndim != 3 or len(codes_NHW) != len(labels_N) or not len(labels_N):
        raise ValueError(
            f"fit_code_judge: expected codes (N, H, W) and N labels, N >= 1; got {tuple(codes_NHW.shape)} "
            f"and {len(labels_N)} labels"
        )
    if int(labels_N.min()) < 0 or int(labels_N.max()) >= num_classes:
        raise ValueError(
            f"fit_code_judge: labels must lie in [0, {num_classes}); got {labels_N.min()}..{labels_N.max()}"
        )
    if not 0 <= noise < 1:
        raise ValueError(f"fit_code_judge: noise must lie in [0, 1); got {noise}")
    device = codes_NHW.device
    num_codes = len(codebook_KD)
    draws = torch.Generator().manual_seed(seed)
    # Callers may sample under no_grad (best of K fits its judge on first use); the fit needs gradients.
    with torch.random.fork_rng(devices=[]), torch.enable_grad():
        torch.manual_seed(seed)
        judge = (judge if judge is not None else CodeJudge(codebook_KD.to(device), num_classes)).to(device)
        optimizer = torch.optim.AdamW(judge.parameters(), lr=2e-3, weight_decay=0.05)
        count = len(labels_N)
        for _ in range(epochs):
            judge.train()
            order = torch.randperm(count, generator=draws)
            for start in range(0, count, batch_size):
                index = order[start : start + batch_size]
                codes = codes_NHW[index.to(device)].clone()
                if noise:
                    share_B11 = noise * torch.rand(len(index), 1, 1, generator=draws)
                    flip = (torch.rand(codes.shape, generator=draws) < share_B11).to(device)
                    replacement = torch.randint(num_codes, codes.shape, generator=draws).to(device)
                    codes = torch.where(flip, replacement, codes)
                loss = F.cross_entropy(judge(codes), labels_N[index].to(device))
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
    return judge.eval()


def codebook_of(tokenizer: Any) -> torch.Tensor:
    """The tokenizer's codebook (K, D): the latent of each code, by the quantizer's own lookup."""
    quantizer = tokenizer.quantizer
    codes_11K = torch.arange(quantizer.codebook_size, device=tokenizer.device).view(1, 1, -1)
    with torch.no_grad():
        return quantizer.lookup(codes_11K)[0, :, 0, :].T.detach().float()


def fit_run_judge(pipeline: Any) -> CodeJudge:
    """The :class:`CodeJudge` of a generation pipeline's run: fitted on the canonical codes of the
    training split the generator learned from (the split ``vqtouch evaluate generation`` holds its
    conditions out of), seeded by the run's seed; about a minute on a CPU.  A ConfigError when the
    run's training samples carry no labels."""
    import sys

    from vqtouch.plugins.evaluation.distribution import labels_of

    from .codes import canonical_background

    train, background_3HW, _ = pipeline.training_split("best of K by the code judge")
    print(f"fitting the code judge on {len(train)} training images (about a minute on a CPU)", file=sys.stderr)
    samples = [train[i] for i in range(len(train))]
    labels = labels_of(samples)
    if labels is None:
        raise ConfigError(
            "best of K by the code judge needs labelled training samples; this run's have none "
            "(use --best-of-rank posterior)"
        )
    tokenizer, device = pipeline.tokenizer, pipeline.device
    with torch.no_grad():
        codes = torch.cat(
            [
                tokenizer.encode_codes(torch.stack([s["tactile"] for s in samples[start : start + 64]]).to(device))
                for start in range(0, len(samples), 64)
            ]
        )
        if background_3HW is not None:
            codes, _ = canonical_background(codes, tokenizer, background_3HW.to(device))
    # Every class a label conditioner can ask for, even one absent from the training split.
    classes = [len(pipeline.class_names or []), max(labels) + 1]
    classes += [c.num_classes for c in pipeline.conditioners if isinstance(getattr(c, "num_classes", None), int)]
    return fit_code_judge(
        codes,
        torch.tensor(labels, device=codes.device),
        codebook_of(tokenizer),
        max(classes),
        seed=pipeline.config.seed,
    )


class JudgeRanker(BestOfRanker):
    """Scores a candidate by the run's code judge's log p(row's class | codes) (:meth:`CodeJudge.rank`);
    the judge is fitted when a pipeline first ranks with it (:func:`fit_run_judge`)."""

    needs_classes = True

    def __init__(self) -> None:
        self.judge: CodeJudge | None = None

    def prepare(self, pipeline: Any) -> None:
        self.judge = fit_run_judge(pipeline)

    def score(self, codes_BHW: torch.Tensor, batch: BestOfBatch) -> torch.Tensor:
        if self.judge is None:
            raise RuntimeError("the judge ranker scores after prepare(pipeline) has fitted its judge")
        return self.judge.rank(codes_BHW, batch.conditions)


def build_judge_ranker(config: Any, context: Any) -> JudgeRanker:
    """The ``judge`` ranker (it has no options)."""
    return JudgeRanker()

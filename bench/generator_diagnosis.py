"""Why does (or doesn't) the generator follow its condition?  The measurements of docs/generation.md.

Run (one job at a time on a 2-core CPU; OMP_NUM_THREADS=2):

    .venv/bin/python bench/generator_diagnosis.py codes                      # the tokenizer's no-contact codes
    .venv/bin/python bench/generator_diagnosis.py overfit --conditioner tactile --minutes 5 [--set KEY=VALUE ...]
    .venv/bin/python bench/generator_diagnosis.py split --bundle tour         # loss / x0 accuracy by region and t
    .venv/bin/python bench/generator_diagnosis.py sensitivity --bundle tour  # does the sample move with its condition?
    .venv/bin/python bench/generator_diagnosis.py gap --bundle tour          # training scenes against held-out ones
    .venv/bin/python bench/generator_diagnosis.py locate --minutes 8 --lr 1e-3 --batch 32  # contact from vision
    .venv/bin/python bench/generator_diagnosis.py cost --conditioner visual_cnn \
        --variant "" --variant "conditioner.grid_context=[1,2,4,8]"   # training step time per setting
    .venv/bin/python bench/generator_diagnosis.py rescore --weights RUN.json.pt --pairs 900 --n 64 --guidance 2
    .venv/bin/python bench/generator_diagnosis.py rerank --conditioner label --candidates 8 --guidance 2  # best of K
    .venv/bin/python bench/generator_diagnosis.py implicit --n 64   # the generator as a classifier of real codes
    .venv/bin/python bench/generator_diagnosis.py judge --conditioner label --candidates 8 --guidance 2 --out F
    .venv/bin/python bench/generator_diagnosis.py rankers --n 100 --candidates 8 --guidance 2 --out F  # label rankings

Everything runs over the bundled ``tour`` tokenizer (``plugins/pretrained/weights/tour``) and the
tour scene's procedural data: GelSight targets, GelSight Mini images of the same contacts as the
tactile condition, aligned visual images, 12 labelled classes.  ``overfit`` trains a fresh
generator and conditioner on a fixed set of training pairs (the whole diagnosis: can the model
learn the mapping at all, and how fast) and scores its samples of those same pairs against the
tokenizer's ceiling and the no-contact background; ``--held-out N`` also renders N more pairs,
never trained on, and scores those unseen conditions; ``--out FILE`` writes the JSON (with the
weights in FILE.pt for ``rescore --weights``).  Prints one JSON object.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F

from vqtouch.core import Assembly, BuildContext, load_plugins, resolve_config
from vqtouch.core.config import parse_override
from vqtouch.plugins.evaluation.contact import contact_mask, contact_region_scores
from vqtouch.plugins.generator.codes import canonical_background, contact_cells
from vqtouch.plugins.pretrained.bundle import load_bundle

#: Conditioners a diagnosis can train, with the sample key each reads.
CONDITIONERS = {
    "tactile": {"name": "tactile"},
    "label": {"name": "label"},
    "visual": {"name": "visual", "input_size": 128},
    "visual_cnn": {"name": "visual_cnn"},
    "text_scratch": {"name": "text_scratch", "vocab_buckets": 1024},
}


#: The procedural seed of the bundle tokenizer's training scenes: overfit, rescore and cost render from it.
TOUR_SEED = 7


def tour_data(host: Any, seed: int, count: int) -> tuple[Any, dict[str, Any]]:
    """The tour scene's dataset (procedural ``seed``) and its first ``count`` samples, batched."""
    config = resolve_config(
        "tour", overrides=[f"data.dataset.seed={seed}", f"data.dataset.num_samples={count}"], host=host
    )
    dataset = Assembly(config, host).component("data.dataset")
    return dataset, dataset.render_batch(list(range(count)))


def background_of(dataset: Any, size: int = 64) -> torch.Tensor:
    """The rendering sensor's no-contact image (3, H, W)."""
    return dataset.sensor.render(torch.zeros(1, size, size), generator=torch.Generator().manual_seed(0))[0]


def contact_tokens(images_B3HW: torch.Tensor, background_3HW: torch.Tensor, grid: int) -> torch.Tensor:
    """(B, grid*grid) bool: code-grid cells that hold any contact pixel."""
    mask_BHW = contact_mask(images_B3HW, background_3HW.expand_as(images_B3HW))
    return F.adaptive_max_pool2d(mask_BHW[:, None].float(), grid)[:, 0].flatten(1) > 0


@torch.no_grad()
def encode(tokenizer: Any, images: torch.Tensor, batch: int = 64) -> torch.Tensor:
    return torch.cat([tokenizer.encode_codes(images[i : i + batch]) for i in range(0, len(images), batch)])


@torch.no_grad()
def decode(tokenizer: Any, codes: torch.Tensor, batch: int = 64) -> torch.Tensor:
    return torch.cat([tokenizer.decode_codes(codes[i : i + batch]) for i in range(0, len(codes), batch)]).clamp(0, 1)


def entropy_bits(codes: torch.Tensor) -> float:
    counts = torch.bincount(codes.flatten()).float()
    p = counts[counts > 0] / counts.sum()
    return float(-(p * p.log2()).sum())


# -- codes: what the tokenizer does to the no-contact area ----------------------------------------


def codes_report(args: argparse.Namespace) -> dict[str, Any]:
    host = load_plugins()
    bundle = load_bundle(args.bundle, host)
    dataset, batch = tour_data(host, args.seed, args.n)
    background = background_of(dataset)
    renders = torch.cat(
        [dataset.sensor.render(torch.zeros(1, 64, 64), generator=torch.Generator().manual_seed(s)) for s in range(64)]
    )
    flat_codes = encode(bundle.tokenizer, renders).flatten(1)  # (64 noise draws, L)
    codes_BL = encode(bundle.tokenizer, batch["tactile"]).flatten(1)
    grid = int(math.isqrt(codes_BL.shape[1]))
    in_contact = contact_tokens(batch["tactile"], background, grid)
    mode_L = flat_codes.mode(dim=0).values
    return {
        "code_grid": grid,
        "codebook_size": bundle.tokenizer.quantizer.codebook_size,
        "no_contact_renders": {
            "distinct_codes": int(flat_codes.unique().numel()),
            "distinct_codes_per_position_mean": float(
                torch.tensor([len(c.unique()) for c in flat_codes.T]).float().mean()
            ),
            "share_of_tokens_not_their_position_mode": float((flat_codes != mode_L).float().mean()),
            "entropy_bits_per_token": entropy_bits(flat_codes),
        },
        "dataset": {
            "images": args.n,
            "contact_token_share": float(in_contact.float().mean()),
            "distinct_codes_background_tokens": int(codes_BL[~in_contact].unique().numel()),
            "distinct_codes_contact_tokens": int(codes_BL[in_contact].unique().numel()),
            "background_tokens_equal_to_no_contact_mode": float((codes_BL == mode_L)[~in_contact].float().mean()),
            "entropy_bits_background_tokens": entropy_bits(codes_BL[~in_contact]),
            "entropy_bits_contact_tokens": entropy_bits(codes_BL[in_contact]),
        },
    }


# -- overfit: can a fresh generator learn a fixed set of pairs? -----------------------------------


def tour_context(tokenizer: Any, num_classes: int) -> BuildContext:
    """What the diagnosis's generators and conditioners are built for: 64 px RGB, a 16 x 16 code grid."""
    codebook = tokenizer.quantizer.codebook_size
    return BuildContext(image_size=64, channels=3, num_classes=num_classes, codebook_size=codebook, code_grid=16)


def build_generator(host: Any, tokenizer: Any, conditioner_name: str, overrides: list[str], num_classes: int) -> tuple:
    """A fresh vq_diffusion generator (the bundle's width and depth unless overridden) and conditioner."""
    generator_cfg: dict[str, Any] = {"name": "vq_diffusion"}
    conditioner_cfg = dict(CONDITIONERS[conditioner_name])
    for text in overrides:
        path, value = parse_override(text)
        target = generator_cfg if path[0] == "model" else conditioner_cfg
        target[path[-1]] = value
    context = tour_context(tokenizer, num_classes)
    generator = host.build("generator", generator_cfg, context)
    conditioner = host.build("conditioner", conditioner_cfg, context)
    return generator, conditioner, generator_cfg, conditioner_cfg


def _condition(conditioner: Any, batch: dict[str, Any], index: torch.Tensor) -> Any:
    value = batch[conditioner.sample_key]
    return [value[int(i)] for i in index] if isinstance(value, list) else value[index]


@torch.no_grad()
def sample_codes(
    host: Any,
    generator: Any,
    conditioner: Any,
    batch: dict[str, Any],
    count: int,
    *,
    steps: int,
    guidance: float,
    seed: int,
    sampler_name: str = "posterior",
    offset: int = 0,
) -> torch.Tensor:
    sampler = host.build("sampler", {"name": sampler_name})
    generator.eval(), conditioner.eval()
    rows = []
    for start in range(0, count, 32):
        index = torch.arange(offset + start, offset + min(count, start + 32))
        condition = conditioner(_condition(conditioner, batch, index))
        draws = [torch.Generator().manual_seed(seed * 100_003 + int(i)) for i in index]
        rows.append(
            generator.sample(
                condition, sampler, steps=steps, null=conditioner.null(len(index)), guidance=guidance, generators=draws
            )
        )
    return torch.cat(rows)


def contact_psnr(
    candidates: dict[str, torch.Tensor], truth: torch.Tensor, background: torch.Tensor
) -> dict[str, float]:
    scores = contact_region_scores(candidates, truth, background.expand_as(truth))
    return {key: round(value, 3) for key, value in scores.items() if key.endswith("contact_psnr")}


def centroid_error_px(images: torch.Tensor, truth: torch.Tensor, background: torch.Tensor) -> float:
    """Mean distance in pixels between the contact-region centroids of images and truth (contact
    weighted by the absolute difference to the background, so a faint contact still has a centre)."""

    def centres(x: torch.Tensor) -> torch.Tensor:
        weight = (x - background).abs().mean(1)
        weight = (weight - weight.flatten(1).median(1).values[:, None, None]).clamp_min(0)
        rows = torch.arange(x.shape[-2]).float()[None, :, None]
        cols = torch.arange(x.shape[-1]).float()[None, None, :]
        total = weight.sum((1, 2)).clamp_min(1e-8)
        return torch.stack([(weight * rows).sum((1, 2)) / total, (weight * cols).sum((1, 2)) / total], 1)

    return float((centres(images) - centres(truth)).norm(dim=1).mean())


def nearest_label_accuracy(
    images: torch.Tensor, labels: torch.Tensor, pool: torch.Tensor, pool_labels: torch.Tensor
) -> float:
    """Share of images whose nearest training image (pixel distance at 16x16, background included)
    has the image's condition label: a crude, classifier-free check that a label is followed."""

    def small(x: torch.Tensor) -> torch.Tensor:
        return F.adaptive_avg_pool2d(x, 16).flatten(1)

    nearest = torch.cdist(small(images), small(pool)).argmin(1)
    return float((pool_labels[nearest] == labels).float().mean())


@torch.no_grad()
def fair_classifier(tokenizer: Any, truth: torch.Tensor, labels: torch.Tensor, pairs: int) -> Any:
    """``vqtouch evaluate generation --classifier-on reconstructions``'s classifier for these scenes,
    fitted on the tokenizer's reconstructions of the ``pairs`` training images (the decoder's look,
    which a classifier fitted on sharp images cannot read), as a function of images generated for
    the held-out scenes after them (one each, in order) to their accuracy and the ceiling: the same
    classifier on the reconstructions of those scenes, computed once."""
    from vqtouch.plugins.evaluation.distribution import RealImageClassifier
    from vqtouch.plugins.evaluation.fd_metric import FdEffNetLite0
    from vqtouch.plugins.tokenizer.loading import reconstruct_all

    features = FdEffNetLite0().pooled_features
    classifier = RealImageClassifier(features(reconstruct_all(tokenizer, truth[:pairs], 64)), labels[:pairs].tolist())
    held_out_labels = labels[pairs:].tolist()
    ceiling = classifier.accuracy(features(reconstruct_all(tokenizer, truth[pairs:], 64)), held_out_labels)

    def score(images: torch.Tensor) -> dict[str, float]:
        return {
            "classifier_accuracy": round(classifier.accuracy(features(images), held_out_labels), 4),
            "ceiling_classifier_accuracy": round(ceiling, 4),
        }

    return score


def pretrain_grid(
    args: argparse.Namespace,
    host: Any,
    tokenizer: Any,
    background: torch.Tensor,
    generator: Any,
    conditioner: Any,
    batch: dict[str, Any],
    contact_NHW: torch.Tensor | None,
) -> dict[str, Any] | None:
    """``overfit --pretrain-steps N``: before the generator trains, the plugin's grid pretraining
    (:func:`~vqtouch.plugins.generator.grid_pretrain.pretrain_condition_grid`, what
    ``generator.train.grid_pretrain`` runs) for N batches of ``--batch``, on the ``--pairs`` training
    scenes and ``--extra-scenes`` newly rendered ones."""
    from vqtouch.plugins.generator.grid_pretrain import GridPretrainConfig, pretrain_condition_grid

    if not args.pretrain_steps:
        return None
    if contact_NHW is None:
        raise SystemExit("overfit --pretrain-steps needs --contact-weight W (W > 0) and --canonical")
    key = conditioner.sample_key
    images, contact = batch[key][: args.pairs], contact_NHW[: args.pairs]
    if args.extra_scenes:
        extra = extra_scenes(host, TOUR_SEED, args.extra_scenes)
        extra_codes, _ = canonical_background(encode(tokenizer, extra["tactile"]), tokenizer, background)
        images = torch.cat([images, extra[key]])
        contact = torch.cat([contact, contact_cells(extra_codes, tokenizer, background)])
    note = pretrain_condition_grid(
        generator,
        [conditioner],
        {key: images},
        contact,
        GridPretrainConfig(steps=args.pretrain_steps),
        [0],
        batch_size=args.batch,
        seed=args.seed,
    )
    print(json.dumps({"pretrain": note}), flush=True)
    return note


def overfit(args: argparse.Namespace) -> dict[str, Any]:
    torch.manual_seed(args.seed)
    host = load_plugins()
    bundle = load_bundle(args.bundle, host)
    tokenizer = bundle.tokenizer
    total = args.pairs + args.held_out
    dataset, batch = tour_data(host, TOUR_SEED, total)
    background = background_of(dataset)
    codes = encode(tokenizer, batch["tactile"])
    changed = 0.0
    if args.contact_weight and not args.canonical:
        raise SystemExit("overfit --contact-weight needs --canonical (the contact cells are the non-background codes)")
    if args.canonical:
        codes, changed = canonical_background(codes, tokenizer, background)
    codes = codes.flatten(1)
    overrides = [*args.set, *([f"model.contact_weight={args.contact_weight}"] if args.contact_weight else [])]
    generator, conditioner, gcfg, ccfg = build_generator(
        host, tokenizer, args.conditioner, overrides, len(dataset.class_names)
    )
    train_index = torch.arange(args.pairs)
    # The contact's place on the code grid (generator.model.contact_weight asks the condition grid for it).
    contact_NHW = contact_cells(codes.view(-1, 16, 16), tokenizer, background) if args.contact_weight else None
    pretrain = pretrain_grid(args, host, tokenizer, background, generator, conditioner, batch, contact_NHW)
    params = [p for m in (generator, conditioner) for p in m.parameters() if p.requires_grad]
    optimizer = torch.optim.AdamW(params, lr=args.lr, betas=(0.9, 0.96), weight_decay=4.5e-2)
    warmup = args.warmup
    schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda s: min(1.0, (s + 1) / warmup) if warmup else 1.0)
    draws = torch.Generator().manual_seed(args.seed)
    log, step, start = [], 0, time.perf_counter()
    while time.perf_counter() - start < args.minutes * 60 and (args.steps == 0 or step < args.steps):
        generator.train(), conditioner.train()
        index = train_index[torch.randint(args.pairs, (args.batch,), generator=draws)]
        drop = torch.rand(args.batch, generator=draws) < 0.1
        condition = conditioner(_condition(conditioner, batch, index), drop)
        contact = {} if contact_NHW is None else {"contact_BHW": contact_NHW[index]}
        loss, scalars = generator.training_loss(codes[index].view(-1, 16, 16), condition, **contact)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 0.5)
        optimizer.step()
        schedule.step()
        step += 1
        if step % 50 == 0:
            log.append(
                {
                    "step": step,
                    "minutes": round((time.perf_counter() - start) / 60, 2),
                    "loss": round(float(loss.detach()), 4),
                    **({"contact_bce": round(scalars["contact_bce"], 4)} if "contact_bce" in scalars else {}),
                }
            )
            print(json.dumps(log[-1]), flush=True)
    minutes = (time.perf_counter() - start) / 60
    result: dict[str, Any] = {
        "conditioner": ccfg,
        "generator": gcfg,
        "pairs": args.pairs,
        "steps": step,
        "canonical_background_cells_changed": round(changed, 4),
        "train_minutes": round(minutes, 2),
        "lr": args.lr,
        "warmup": warmup,
        "contact_weight": args.contact_weight,
        "pretrain": pretrain,
        "log": log,
    }
    truth = batch["tactile"]
    scorer = None
    if args.conditioner in ("label", "text_scratch") and args.held_out:
        scorer = fair_classifier(tokenizer, truth, batch["label"], args.pairs)
    for name, offset, count in (("train", 0, min(args.pairs, 64)), ("held_out", args.pairs, args.held_out)):
        if not count:
            continue
        sampled = sample_codes(
            host,
            generator,
            conditioner,
            batch,
            count,
            steps=args.sample_steps,
            guidance=args.guidance,
            seed=1,
            offset=offset,
        )
        rows = slice(offset, offset + count)
        images = decode(tokenizer, sampled)
        result[name] = {
            "token_accuracy": round(float((sampled.flatten(1) == codes[rows]).float().mean()), 4),
            **contact_psnr(
                {
                    "": images,
                    "ceiling_": decode(tokenizer, codes[rows].view(-1, 16, 16)),
                    "background_": background.expand_as(truth[rows]),
                },
                truth[rows],
                background,
            ),
            "centroid_error_px": round(centroid_error_px(images, truth[rows], background), 2),
            "nearest_training_image_label_accuracy": round(
                nearest_label_accuracy(images, batch["label"][rows], truth[: args.pairs], batch["label"][: args.pairs]),
                3,
            ),
        }
        if scorer is not None and name == "held_out":
            result[name] |= scorer(images)
    result |= split_scores(generator, conditioner, batch, codes, background, train_index[:64])
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=1))
        torch.save(
            {
                "generator": generator.state_dict(),
                "conditioner": conditioner.state_dict(),
                "generator_cfg": gcfg,
                "conditioner_cfg": ccfg,
            },
            args.out + ".pt",
        )
    return result


@torch.no_grad()
def split_scores(
    generator: Any,
    conditioner: Any,
    batch: dict[str, Any],
    codes: torch.Tensor,
    background: torch.Tensor,
    index: torch.Tensor,
) -> dict[str, Any]:
    """Cross-entropy and x0 accuracy of masked tokens, split by contact/background token and by t
    (five bins), from the condition and from the null condition."""
    generator.eval(), conditioner.eval()
    schedule, steps = generator.schedule, generator.config.num_steps
    in_contact = contact_tokens(batch["tactile"][index], background, 16)
    out: dict[str, Any] = {}
    for label, drop in (("conditioned", False), ("null", True)):
        rows = []
        for t in range(0, steps, max(1, steps // 20)):
            t_B = torch.full((len(index),), t)
            noised = schedule.q_sample(codes[index], t_B, torch.Generator().manual_seed(t))
            condition = conditioner(_condition(conditioner, batch, index), torch.full((len(index),), drop))
            logits = generator.network(noised, t_B, condition=condition.tokens_BND, condition_grid=condition.grid_BDhw)
            nll = F.cross_entropy(logits, codes[index], reduction="none")
            correct = (logits.argmax(1) == codes[index]).float()
            masked = noised == schedule.mask_index
            for region, where in (("contact", in_contact), ("background", ~in_contact)):
                sel = masked & where
                if sel.any():
                    rows.append((t, region, float(nll[sel].mean()), float(correct[sel].mean())))
        table = {}
        for lo in range(0, steps, steps // 5):
            for region in ("contact", "background"):
                picked = [r for r in rows if lo <= r[0] < lo + steps // 5 and r[1] == region]
                if picked:
                    table[f"t{lo}-{lo + steps // 5 - 1}:{region}"] = {
                        "ce": round(sum(r[2] for r in picked) / len(picked), 3),
                        "x0_acc": round(sum(r[3] for r in picked) / len(picked), 3),
                    }
        out[f"split_{label}"] = table
    return out


def load_bundle_pair(host: Any, name: str, conditioner_name: str) -> tuple[Any, Any, Any]:
    bundle = load_bundle(name, host)
    index = bundle.conditioner_names.index(conditioner_name)
    return bundle.tokenizer, bundle.generator.float(), bundle.conditioners[index].float()


def split(args: argparse.Namespace) -> dict[str, Any]:
    host = load_plugins()
    tokenizer, generator, conditioner = load_bundle_pair(host, args.bundle, args.conditioner)
    dataset, batch = tour_data(host, 0, 64)
    background = background_of(dataset)
    codes = encode(tokenizer, batch["tactile"]).flatten(1)
    return {
        "bundle": args.bundle,
        "conditioner": args.conditioner,
        **split_scores(generator, conditioner, batch, codes, background, torch.arange(64)),
    }


def sensitivity(args: argparse.Namespace) -> dict[str, Any]:
    """Sample each held-out condition, and the same draws with the conditions shuffled: does the
    sample's contact centre follow its own condition's truth, or the shuffled one's?"""
    host = load_plugins()
    tokenizer, generator, conditioner = load_bundle_pair(host, args.bundle, args.conditioner)
    dataset, batch = tour_data(host, 0, args.n)
    background = background_of(dataset)
    truth = batch["tactile"]
    images = decode(
        tokenizer,
        sample_codes(
            host, generator, conditioner, batch, args.n, steps=args.sample_steps, guidance=args.guidance, seed=1
        ),
    )
    permutation = torch.roll(torch.arange(args.n), 1)
    shuffled_batch = {
        k: ([v[int(i)] for i in permutation] if isinstance(v, list) else v[permutation]) for k, v in batch.items()
    }
    shuffled = decode(
        tokenizer,
        sample_codes(
            host,
            generator,
            conditioner,
            shuffled_batch,
            args.n,
            steps=args.sample_steps,
            guidance=args.guidance,
            seed=1,
        ),
    )
    return {
        "bundle": args.bundle,
        "conditioner": args.conditioner,
        "n": args.n,
        "centroid_error_px_to_own_truth": round(centroid_error_px(images, truth, background), 2),
        "centroid_error_px_shuffled_condition_to_own_truth": round(centroid_error_px(shuffled, truth, background), 2),
        "centroid_error_px_shuffled_condition_to_its_truth": round(
            centroid_error_px(shuffled, truth[permutation], background), 2
        ),
        "mean_abs_change_when_condition_changes": round(float((images - shuffled).abs().mean()), 4),
        "mean_abs_truth_difference_between_conditions": round(float((truth - truth[permutation]).abs().mean()), 4),
    }


def bundle_split(name: str, host: Any) -> tuple[Any, Any, Any, Any, torch.Tensor]:
    """The bundle's pipeline, its dataset, the (train, held-out) split ``vqtouch evaluate generation
    --run pretrained:NAME`` uses, and the no-contact background (3, H, W) it scores against."""
    from vqtouch.plugins.utils.splits import experiment_split
    from vqtouch.core.image_size import image_hw
    from vqtouch.plugins.evaluation.contact import dataset_background
    from vqtouch.plugins.generator.pipeline import load_pipeline

    pipe = load_pipeline(f"pretrained:{name}", host=host)
    dataset = Assembly(pipe.config, host).component("data.dataset")
    train, held_out = experiment_split(dataset, pipe.config.data, pipe.config.seed)
    background_3HW, _ = dataset_background(train, image_hw(pipe.config.data.image_size))
    return pipe, dataset, train, held_out, background_3HW


@torch.no_grad()
def head(args: argparse.Namespace) -> dict[str, Any]:
    """Where the bundle's contact head (``generator.model.contact_weight``) puts the contact, read
    straight from the condition grid before any sampling: the centre of its contact probabilities on
    the code grid (each raised to a power, which favours its surest cells), in pixels, against the
    truth's contact centre, on the held-out conditions ``vqtouch evaluate generation`` scores.  The
    same centre of the truth's own contact cells (the head's training target) is the floor of a map
    at the code grid's resolution."""
    from vqtouch.plugins.evaluation.contact import contact_centroids

    pipe, dataset, _, held_out, background_3HW = bundle_split(args.bundle, load_plugins())
    generator = pipe.generator.float()
    if generator.contact_head is None:
        raise SystemExit(f"bundle {args.bundle!r}'s generator has no contact head (generator.model.contact_weight=0)")
    count = min(args.n, len(held_out))
    batch = dataset.render_batch([held_out.indices[i] for i in range(count)])
    truth = batch["tactile"]
    truth_B2 = contact_centroids(truth, background_3HW.expand_as(truth))
    height, width = generator.network.grid_hw
    scale = truth.shape[-1] / width

    def map_error(weight_BHW: torch.Tensor) -> float:
        rows = (torch.arange(height).float() + 0.5) * scale - 0.5
        cols = (torch.arange(width).float() + 0.5) * scale - 0.5
        total = weight_BHW.sum((1, 2)).clamp_min(1e-12)
        row_B = (weight_BHW * rows[None, :, None]).sum((1, 2)) / total
        col_B = (weight_BHW * cols[None, None, :]).sum((1, 2)) / total
        centre_B2 = torch.stack([row_B, col_B], 1)
        return round(float((centre_B2 - truth_B2).norm(dim=1).mean()), 2)

    codes = canonical_background(encode(pipe.tokenizer, truth), pipe.tokenizer, background_3HW)[0]
    cells_BHW = contact_cells(codes, pipe.tokenizer, background_3HW).float()
    out: dict[str, Any] = {"bundle": args.bundle, "n": count, "true_contact_cells_px": map_error(cells_BHW)}
    for name, conditioner in zip(pipe.conditioner_names(), pipe.conditioners):
        conditioner = conditioner.float().eval()
        condition = conditioner(_condition(conditioner, batch, torch.arange(count)))
        if condition.grid_BDhw is None:
            continue
        embedding_BLd = generator.network.grid_embedding(condition.grid_BDhw)
        p_BHW = torch.sigmoid(generator.contact_head(embedding_BLd).squeeze(-1).float()).view(count, height, width)
        out[name] = {
            **{f"head_power{power}_px": map_error(p_BHW**power) for power in (1, 2, 4, 8)},
            # The epsilon puts a map with no cell over 0.5 at the grid's centre, the guess without a condition.
            "head_thresholded_px": map_error((p_BHW > 0.5).float() + 1e-6),
            "bce_against_true_cells": round(float(F.binary_cross_entropy(p_BHW, cells_BHW)), 4),
        }
    return out


@torch.no_grad()
def prior(args: argparse.Namespace) -> dict[str, Any]:
    """Sampling with the contact head as a layout prior (``--conditioner``, one with a grid): at every
    step, a code cell the head calls background with probability above 1 - tau gets its x0
    distribution replaced by a one-hot at the guided distribution's most likely code (the canonical
    background makes that the no-contact image's code wherever the generator agrees), so the
    sampler draws the contact only where the head leaves room for it.  Per tau: the contact-centroid
    error and contact PSNR of ``vqtouch evaluate generation`` on its held-out conditions, one sampling
    seed per ``--sample-seeds``; tau 0 is plain sampling."""
    from vqtouch.plugins.evaluation.contact import contact_centroid_errors

    host = load_plugins()
    pipe, dataset, _, held_out, background_3HW = bundle_split(args.bundle, host)
    generator = pipe.generator.float()
    names = pipe.conditioner_names()
    # The pipeline names its conditioners "INDEX:NAME".
    conditioner = pipe.conditioners[[name.split(":")[-1] for name in names].index(args.conditioner)].float().eval()
    count = min(args.n, len(held_out))
    batch = dataset.render_batch([held_out.indices[i] for i in range(count)])
    truth = batch["tactile"]
    background = background_3HW.expand_as(truth)
    sampler = host.build("sampler", {"name": "posterior"})
    network = generator.network
    plain_forward = network.forward
    out: dict[str, Any] = {"bundle": args.bundle, "conditioner": args.conditioner, "n": count, "by_tau": {}}
    for tau in args.taus:
        by_seed = {}
        for seed in args.sample_seeds:
            rows = []
            for start in range(0, count, 32):
                index = torch.arange(start, min(count, start + 32))
                condition = conditioner(_condition(conditioner, batch, index))
                embedding_BLd = network.grid_embedding(condition.grid_BDhw)
                p_BL = torch.sigmoid(generator.contact_head(embedding_BLd).squeeze(-1).float())
                fixed_BL = p_BL < tau

                def forward(
                    codes_BL: torch.Tensor, t_B: torch.Tensor, fixed_BL=fixed_BL, **kwargs: Any
                ) -> torch.Tensor:
                    logits_BKL = plain_forward(codes_BL, t_B, **kwargs)
                    if not bool(fixed_BL.any()):
                        return logits_BKL
                    rows_fixed = fixed_BL.repeat(len(codes_BL) // len(fixed_BL), 1)
                    # The conditional half's choice (the first rows under guidance) for every copy.
                    best_BL = logits_BKL[: len(fixed_BL)].argmax(1).repeat(len(codes_BL) // len(fixed_BL), 1)
                    one_hot_BKL = torch.full_like(logits_BKL, -1e4).scatter_(1, best_BL[:, None], 0.0)
                    return torch.where(rows_fixed[:, None], one_hot_BKL, logits_BKL)

                network.forward = forward
                try:
                    draws = [torch.Generator().manual_seed(seed * 100_003 + int(i)) for i in index]
                    rows.append(
                        generator.sample(
                            condition,
                            sampler,
                            steps=args.sample_steps,
                            null=conditioner.null(len(index)),
                            guidance=args.guidance,
                            generators=draws,
                        )
                    )
                finally:
                    del network.forward
            images = decode(pipe.tokenizer, torch.cat(rows))
            scores = contact_centroid_errors({"": images}, truth, background)
            by_seed[seed] = {
                "centroid_error_px": round(scores["contact_centroid_error_px"], 2),
                **contact_psnr({"": images}, truth, background_3HW),
            }
        errors = [row["centroid_error_px"] for row in by_seed.values()]
        out["by_tau"][str(tau)] = {"by_seed": by_seed, "centroid_error_px_mean": round(sum(errors) / len(errors), 2)}
        print(json.dumps({str(tau): out["by_tau"][str(tau)]}), flush=True)
    return out


def gap(args: argparse.Namespace) -> dict[str, Any]:
    """The bundle's masked-token cross-entropy and x0 accuracy (all t, conditioned) on ``--n`` of its
    own training scenes against ``--n`` of its held-out ones (the split ``vqtouch evaluate generation``
    scores), per conditioner: a generalisation gap says the generator learnt its scenes rather than
    the mapping, and more scenes would help."""
    pipe, dataset, train, held_out, background_3HW = bundle_split(args.bundle, load_plugins())
    count = min(args.n, len(train), len(held_out))
    out: dict[str, Any] = {"bundle": args.bundle, "n": count}
    for split_name, subset in (("train", train), ("held_out", held_out)):
        batch = dataset.render_batch([subset.indices[i] for i in range(count)])
        # The targets the generator trained on: canonical-background codes.
        codes = canonical_background(encode(pipe.tokenizer, batch["tactile"]), pipe.tokenizer, background_3HW)[0]
        codes = codes.flatten(1)
        for name, conditioner in zip(pipe.conditioner_names(), pipe.conditioners):
            table = split_scores(
                pipe.generator.float(), conditioner.float(), batch, codes, background_3HW, torch.arange(count)
            )["split_conditioned"]
            for region in ("contact", "background"):
                rows = [v for k, v in table.items() if k.endswith(region)]
                out[f"{name}:{region}:{split_name}"] = {
                    "ce": round(sum(r["ce"] for r in rows) / len(rows), 3),
                    "x0_acc": round(sum(r["x0_acc"] for r in rows) / len(rows), 3),
                }
    return out


# -- locate: how well can the visual image place the contact at all? ----------------------------


class ContactLocator(torch.nn.Module):
    """A small CNN that reads a visual image and returns where the tactile contact's centre lies: a
    heat map over the image, soft-argmaxed to (row, column) pixels at the tactile image's size.  It
    is trained on the centre alone, the one thing the centroid score asks of a sample."""

    def __init__(self, width: int = 48) -> None:
        super().__init__()

        def block(c_in: int, c_out: int, dilation: int = 1, stride: int = 1) -> torch.nn.Module:
            return torch.nn.Sequential(
                torch.nn.Conv2d(c_in, c_out, 3, stride=stride, padding=dilation, dilation=dilation),
                torch.nn.GroupNorm(8, c_out),
                torch.nn.SiLU(),
            )

        self.net = torch.nn.Sequential(
            block(5, width, stride=2),
            block(width, width, 2),
            block(width, width, 4),
            block(width, width, 8),
            block(width, width, 16),
            block(width, width, 1),
            torch.nn.Conv2d(width, 1, 1),
        )

    def forward(self, visual_B3HW: torch.Tensor, out_hw: tuple[int, int]) -> torch.Tensor:
        height, width = visual_B3HW.shape[-2:]
        rows = torch.linspace(-1, 1, height).view(1, 1, -1, 1).expand(len(visual_B3HW), 1, height, width)
        cols = torch.linspace(-1, 1, width).view(1, 1, 1, -1).expand(len(visual_B3HW), 1, height, width)
        logits_BHW = self.net(torch.cat([visual_B3HW, rows, cols], 1))[:, 0]
        weights_BHW = logits_BHW.flatten(1).softmax(1).view_as(logits_BHW)
        height, width = logits_BHW.shape[-2:]
        # Pixel centres of the input mapped onto the tactile image's pixel grid.
        grid_rows = torch.linspace(0, out_hw[0] - 1, height).view(1, -1, 1)
        grid_cols = torch.linspace(0, out_hw[1] - 1, width).view(1, 1, -1)
        return torch.stack([(weights_BHW * grid_rows).sum((1, 2)), (weights_BHW * grid_cols).sum((1, 2))], 1)


def extra_scenes(host: Any, seed: int, count: int) -> dict[str, torch.Tensor]:
    """``count`` newly rendered tour scenes for a run whose scenes come from procedural ``seed`` (the
    dataset's :meth:`new_scenes`, so none is one of its training or held-out scenes): a batch of
    ``visual``, ``tactile`` and ``label``."""
    config = resolve_config("tour", overrides=[f"data.dataset.seed={seed}"], host=host)
    return Assembly(config, host).component("data.dataset").new_scenes(count).render_batch(list(range(count)))


def locate(args: argparse.Namespace) -> dict[str, Any]:
    """Train :class:`ContactLocator` on the bundle's training scenes (plus ``--extra-scenes`` newly
    rendered ones) for ``--minutes``, and score it on the held-out conditions that ``vqtouch evaluate
    generation --run pretrained:NAME`` scores, with the same contact-centroid definition: a bound
    on what any vision-to-touch generator trained on that data can reach on that score."""
    from vqtouch.plugins.evaluation.contact import contact_centroids

    torch.manual_seed(args.seed)
    host = load_plugins()
    pipe, dataset, train, held_out, background_3HW = bundle_split(args.bundle, host)
    config = pipe.config
    started = time.perf_counter()
    train_batch = dataset.render_batch(list(train.indices))
    test_batch = dataset.render_batch([held_out.indices[i] for i in range(min(args.n, len(held_out)))])
    visual, truth = train_batch["visual"], train_batch["tactile"]
    if args.extra_scenes:
        extra = extra_scenes(host, config.data.dataset.seed, args.extra_scenes)
        visual, truth = torch.cat([visual, extra["visual"]]), torch.cat([truth, extra["tactile"]])
    render_seconds = time.perf_counter() - started
    out_hw = tuple(truth.shape[-2:])
    target_B2 = contact_centroids(truth, background_3HW.expand_as(truth))
    test_target_B2 = contact_centroids(test_batch["tactile"], background_3HW.expand_as(test_batch["tactile"]))
    reconstructions = decode(pipe.tokenizer, encode(pipe.tokenizer, test_batch["tactile"]))

    def error(centres_B2: torch.Tensor) -> float:
        return round(float((centres_B2 - test_target_B2).norm(dim=1).mean()), 2)

    model = ContactLocator(args.width)
    optimiser = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=1e-4)
    steps, history, deadline = 0, [], time.perf_counter() + 60 * args.minutes
    generator = torch.Generator().manual_seed(args.seed)
    while time.perf_counter() < deadline and (args.steps == 0 or steps < args.steps):
        pick = torch.randint(len(visual), (args.batch,), generator=generator)
        loss = (model(visual[pick], out_hw) - target_B2[pick]).norm(dim=1).mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        steps += 1
        if steps % 200 == 0:
            model.eval()
            with torch.no_grad():
                history.append(
                    {
                        "step": steps,
                        "train_px": round(float(loss), 2),
                        "held_out_px": error(model(test_batch["visual"], out_hw)),
                    }
                )
            model.train()
    model.eval()
    with torch.no_grad():
        predicted_B2 = model(test_batch["visual"], out_hw)
    return {
        "bundle": args.bundle,
        "n_held_out": len(test_target_B2),
        "training_scenes": len(visual),
        "render_seconds": round(render_seconds, 1),
        "train_seconds": round(time.perf_counter() - started - render_seconds, 1),
        "steps": steps,
        "centroid_error_px": {
            "locator_from_visual": error(predicted_B2),
            "image_centre": error(torch.tensor([(out_hw[0] - 1) / 2, (out_hw[1] - 1) / 2]).expand_as(test_target_B2)),
            "mean_training_centre": error(target_B2.mean(0).expand_as(test_target_B2)),
            "tokenizer_reconstruction": error(
                contact_centroids(reconstructions, background_3HW.expand_as(reconstructions))
            ),
        },
        "history": history,
    }


def rescore(args: argparse.Namespace) -> dict[str, Any]:
    """Sample the held-out conditions of an ``overfit --held-out N --out FILE`` run again from its
    weights (``--weights FILE.pt``) with each of ``--sample-seeds``: the contact-centroid error and
    contact PSNR per sampling seed, so a difference between two runs can be read against the spread
    the sampler alone makes.  The conditions are the ``--n`` scenes after the first ``--pairs``:
    the run's own held-out ones with its ``--pairs``, other unseen scenes with a larger one (two
    runs with different ``--pairs`` are compared on the same scenes that way)."""
    host = load_plugins()
    tokenizer = load_bundle(args.bundle, host).tokenizer
    dataset, batch = tour_data(host, TOUR_SEED, args.pairs + args.n)  # overfit's scenes, in its order
    background = background_of(dataset)
    truth = batch["tactile"][args.pairs :]
    state = torch.load(args.weights, weights_only=False)
    context = tour_context(tokenizer, len(dataset.class_names))
    generator = host.build("generator", state["generator_cfg"], context)
    conditioner = host.build("conditioner", state["conditioner_cfg"], context)
    generator.load_state_dict(state["generator"])
    conditioner.load_state_dict(state["conditioner"])
    scorer = None
    if state["conditioner_cfg"]["name"] in ("label", "text_scratch"):
        scorer = fair_classifier(tokenizer, batch["tactile"], batch["label"], args.pairs)
    by_seed = {}
    for seed in args.sample_seeds:
        codes = sample_codes(
            host,
            generator,
            conditioner,
            batch,
            args.n,
            steps=args.sample_steps,
            guidance=args.guidance,
            seed=seed,
            offset=args.pairs,
        )
        images = decode(tokenizer, codes)
        by_seed[seed] = {
            "centroid_error_px": round(centroid_error_px(images, truth, background), 2),
            **contact_psnr({"": images}, truth, background),
            **(scorer(images) if scorer is not None else {}),
        }
    errors = [row["centroid_error_px"] for row in by_seed.values()]
    return {
        "weights": args.weights,
        "n": args.n,
        "guidance": args.guidance,
        "by_sampling_seed": by_seed,
        "centroid_error_px_mean": round(sum(errors) / len(errors), 2),
    }


# -- rerank: best of K samples, by the generator's own scores ------------------------------------


@torch.no_grad()
def implicit(args: argparse.Namespace) -> dict[str, Any]:
    """The bundle's generator as a classifier of real images: the share of the ``--n`` held-out
    scenes of ``vqtouch evaluate generation`` whose canonical codes get their own class from the
    arg max of ``--best-of``'s class posterior (what best of K ranks candidates by)."""
    from vqtouch.plugins.generator.posterior import class_log_posteriors

    pipe, dataset, _, held_out, background_3HW = bundle_split(args.bundle, load_plugins())
    names = [name.split(":")[-1] for name in pipe.conditioner_names()]  # the pipeline says "INDEX:NAME"
    conditioner = pipe.conditioners[names.index("label")].float().eval()
    count = min(args.n, len(held_out))
    batch = dataset.render_batch([held_out.indices[i] for i in range(count)])
    codes = canonical_background(encode(pipe.tokenizer, batch["tactile"]), pipe.tokenizer, background_3HW)[0]
    predicted = class_log_posteriors(pipe.generator.float().eval(), conditioner, codes).argmax(0)
    return {
        "bundle": args.bundle,
        "n": count,
        "accuracy": round(float((predicted == batch["label"]).float().mean()), 4),
    }


@torch.no_grad()
def draw_candidate(
    generator: Any, sampler: Any, condition: Any, null: Any, index: torch.Tensor, k: int, args: argparse.Namespace
) -> torch.Tensor:
    """Candidate ``k`` (B, L) of the held-out conditions ``index``: row i drawn with seed k * 100003 + i
    (``rerank`` and ``judge`` draw the same candidates)."""
    draws = [torch.Generator().manual_seed(k * 100_003 + int(i)) for i in index]
    return generator.sample(
        condition, sampler, steps=args.sample_steps, null=null, guidance=args.guidance, generators=draws
    ).flatten(1)


@torch.no_grad()
def cached_candidates(
    args: argparse.Namespace,
    host: Any,
    generator: Any,
    conditioner: Any,
    condition_of: Any,
    first: int,
    stop: int,
    chunk: int,
) -> torch.Tensor:
    """(N, K, L) codes: ``--candidates`` samples (:func:`draw_candidate`'s seeds) for each condition
    index in [first, stop), ``condition_of(index)`` giving the conditioner's input, ``chunk``
    conditions at a time; read from ``--out``.pt when it exists, else drawn and written there."""
    cache = Path(args.out + ".pt") if args.out else None
    if cache is not None and cache.exists():
        return torch.load(cache)
    sampler = host.build("sampler", {"name": "posterior"})
    candidates = []
    for k in range(args.candidates):
        rows = []
        for start in range(first, stop, chunk):
            index = torch.arange(start, min(stop, start + chunk))
            condition = conditioner(condition_of(index))
            rows.append(draw_candidate(generator, sampler, condition, conditioner.null(len(index)), index, k, args))
        candidates.append(torch.cat(rows))
        print(json.dumps({"candidate": k}), flush=True)
    codes_NKL = torch.stack(candidates, 1)
    if cache is not None:
        torch.save(codes_NKL, cache)
    return codes_NKL


def rerank(args: argparse.Namespace) -> dict[str, Any]:
    """Best of ``--candidates`` samples per held-out condition, chosen by the bundle generator's own
    scores (no other model): for the label, its implicit class posterior (log p(x | class) of every
    class, normalised over the classes, at the asked class); for every conditioner, the pointwise
    mutual information log p(x | condition) - log p(x | null); for a conditioner with a grid, the
    contact head's log-likelihood of the candidate's contact cells.  Both likelihoods are the
    generator's ``masked_log_likelihood`` (``--best-of``'s, at t = 20, 40, 60, 80).  Reported: each candidate's score as
    ``vqtouch evaluate generation`` computes it (label: the classifier fitted on the tokenizer's
    reconstructions of the bundle's training images; visual: the contact-centroid error), and the
    best-of-k score over disjoint groups of k candidates, with the seconds per condition of sampling
    and of scoring one candidate."""
    from vqtouch.plugins.evaluation.contact import contact_centroids
    from vqtouch.plugins.evaluation.distribution import RealImageClassifier
    from vqtouch.plugins.evaluation.fd_metric import FdEffNetLite0
    from vqtouch.plugins.generator.posterior import class_log_posteriors
    from vqtouch.plugins.tokenizer.loading import reconstruct_all

    host = load_plugins()
    pipe, dataset, train, held_out, background_3HW = bundle_split(args.bundle, host)
    tokenizer, generator = pipe.tokenizer, pipe.generator.float().eval()
    names = [name.split(":")[-1] for name in pipe.conditioner_names()]  # the pipeline says "INDEX:NAME"
    conditioner = pipe.conditioners[names.index(args.conditioner)].float().eval()
    count = min(args.n, len(held_out))
    batch = dataset.render_batch([held_out.indices[i] for i in range(count)])
    truth, labels = batch["tactile"], batch["label"]
    background = background_3HW.expand_as(truth)
    sampler = host.build("sampler", {"name": "posterior"})
    is_label = args.conditioner == "label"
    candidates, scores = [], {"pmi": [], **({"class_posterior": []} if is_label else {})}
    seconds = {"sampling": 0.0, "scoring": 0.0}
    if not is_label and generator.contact_head is not None:
        scores["contact_head"] = []
    for k in range(args.candidates):
        rows = []
        for store in scores.values():
            store.append(torch.zeros(count))
        for start in range(0, count, 32):
            index = torch.arange(start, min(count, start + 32))
            condition = conditioner(_condition(conditioner, batch, index))
            null = conditioner.null(len(index))
            clock = time.perf_counter()
            codes_BL = draw_candidate(generator, sampler, condition, null, index, k, args)
            seconds["sampling"] += time.perf_counter() - clock
            clock = time.perf_counter()
            codes_BHW = codes_BL.view(-1, *generator.grid_hw)
            scores["pmi"][k][index] = generator.masked_log_likelihood(
                codes_BHW, condition
            ) - generator.masked_log_likelihood(codes_BHW, null)
            if is_label:
                scores["class_posterior"][k][index] = class_log_posteriors(generator, conditioner, codes_BHW)[
                    labels[index], torch.arange(len(index))
                ]
            if "contact_head" in scores:
                p_BL = torch.sigmoid(
                    generator.contact_head(generator.network.grid_embedding(condition.grid_BDhw)).squeeze(-1).float()
                ).clamp(1e-6, 1 - 1e-6)
                cells_BL = contact_cells(codes_BL.view(-1, 16, 16), tokenizer, background_3HW).flatten(1).float()
                scores["contact_head"][k][index] = (cells_BL * p_BL.log() + (1 - cells_BL) * (1 - p_BL).log()).sum(1)
            seconds["scoring"] += time.perf_counter() - clock
            rows.append(codes_BL)
        candidates.append(torch.cat(rows))
        print(json.dumps({"candidate": k, "seconds": {key: round(v, 1) for key, v in seconds.items()}}), flush=True)
    codes_NKL = torch.stack(candidates, 1)
    if is_label:
        features = FdEffNetLite0().pooled_features
        train_batch = dataset.render_batch([train.indices[i] for i in range(len(train))])
        classifier = RealImageClassifier(
            features(reconstruct_all(tokenizer, train_batch["tactile"], 64)), train_batch["label"].tolist()
        )
        # Per image: 1 when the classifier names its condition's class (the mean is the accuracy).
        score_NK = torch.stack(
            [
                torch.tensor(classifier.predict(features(decode(tokenizer, codes_NKL[:, k].view(-1, 16, 16)))))
                == labels
                for k in range(args.candidates)
            ],
            1,
        ).float()
    else:
        truth_N2 = contact_centroids(truth, background)
        # Per image: pixels between its contact centre and the truth's (the mean is the centroid error).
        score_NK = torch.stack(
            [
                (contact_centroids(decode(tokenizer, codes_NKL[:, k].view(-1, 16, 16)), background) - truth_N2).norm(
                    dim=1
                )
                for k in range(args.candidates)
            ],
            1,
        )
    metric = "classifier_accuracy" if is_label else "centroid_error_px"
    rows_N = torch.arange(count)
    out: dict[str, Any] = {
        "bundle": args.bundle,
        "conditioner": args.conditioner,
        "n": count,
        "guidance": args.guidance,
        "metric": metric,
        "each_candidate": [round(float(v), 4) for v in score_NK.mean(0)],
        "seconds_per_condition": {key: round(v / (count * args.candidates), 3) for key, v in seconds.items()},
        "best_of": {},
    }
    group = 1
    while group <= args.candidates:
        out["best_of"][group] = {}
        for name, per_candidate in scores.items():
            score_matrix_NK = torch.stack(per_candidate, 1)
            values = []
            for first in range(0, args.candidates - group + 1, group):
                chosen_N = score_matrix_NK[:, first : first + group].argmax(1) + first
                values.append(round(float(score_NK[rows_N, chosen_N].mean()), 4))
            out["best_of"][group][name] = {"groups": values, "mean": round(sum(values) / len(values), 4)}
        group *= 2
    return out


# -- judge: best of K samples, by a classifier of codes trained on the generator's training codes --


def learned_embedding_judge(codebook_KD: torch.Tensor, num_classes: int) -> torch.nn.Module:
    """The ablation of ``judge --judge-learned``: the plugin's judge with its frozen codebook replaced by
    trained 32-wide code embeddings."""
    from vqtouch.plugins.generator.judge import CodeJudge

    model = CodeJudge(codebook_KD, num_classes)
    model.embed = torch.nn.Embedding(len(codebook_KD), 32)
    first = model.net[0]
    model.net[0] = torch.nn.Conv2d(32, first.out_channels, 3, padding=1)
    return model


def judge(args: argparse.Namespace) -> dict[str, Any]:
    """Best of ``--candidates`` label samples per held-out condition, chosen by the code judge
    (:mod:`vqtouch.plugins.generator.judge`) fitted on the canonical codes of the bundle's training
    scenes (never on images, never on the held-out scenes), once per ``--judge-noise``, ``--judge-data``
    and ``--judge-seeds``.  ``--judge-data``: ``training`` (the plugin's: the training scenes'
    codes), ``hflip`` (and the codes of the same images mirrored left to right), ``extra`` (and
    ``--extra-scenes`` newly rendered scenes' codes); a larger set gets proportionally fewer epochs,
    so every fit passes over as many grids.  Candidates are cached in ``--out``.pt.  Reported: the
    judge's accuracy on the held-out scenes' real codes, each candidate's score by the evaluation's
    classifier (fitted on the tokenizer's reconstructions of the training images), and best of k
    (per fit and, over the seeds, the mean best of all)."""
    from vqtouch.plugins.evaluation.distribution import RealImageClassifier
    from vqtouch.plugins.evaluation.fd_metric import FdEffNetLite0
    from vqtouch.plugins.generator.judge import codebook_of, fit_code_judge
    from vqtouch.plugins.tokenizer.loading import reconstruct_all

    host = load_plugins()
    pipe, dataset, train, held_out, background_3HW = bundle_split(args.bundle, host)
    tokenizer, generator = pipe.tokenizer, pipe.generator.float().eval()
    names = [name.split(":")[-1] for name in pipe.conditioner_names()]
    conditioner = pipe.conditioners[names.index(args.conditioner)].float().eval()
    count = min(args.n, len(held_out))
    batch = dataset.render_batch([held_out.indices[i] for i in range(count)])
    truth, labels = batch["tactile"], batch["label"]
    train_batch = dataset.render_batch([train.indices[i] for i in range(len(train))])
    train_labels = train_batch["label"]
    num_classes = len(dataset.class_names)

    def canonical_codes(images: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            return canonical_background(encode(tokenizer, images), tokenizer, background_3HW)[0]

    train_codes, held_codes = canonical_codes(train_batch["tactile"]), canonical_codes(truth)
    fit_sets: dict[str, tuple[torch.Tensor, torch.Tensor]] = {}
    for name in args.judge_data:
        if name == "training":
            fit_sets[name] = (train_codes, train_labels)
        elif name == "hflip":
            mirrored = canonical_codes(train_batch["tactile"].flip(-1))
            fit_sets[name] = (torch.cat([train_codes, mirrored]), torch.cat([train_labels, train_labels]))
        elif name == "extra":
            if not args.extra_scenes:
                raise SystemExit("judge --judge-data extra needs --extra-scenes N (N > 0)")
            extra = extra_scenes(host, pipe.config.data.dataset.seed, args.extra_scenes)
            fit_sets[name] = (
                torch.cat([train_codes, canonical_codes(extra["tactile"])]),
                torch.cat([train_labels, extra["label"]]),
            )
        else:
            raise SystemExit(f"judge --judge-data {name!r}: choose from training, hflip, extra")
    codes_NKL = cached_candidates(
        args, host, generator, conditioner, lambda index: _condition(conditioner, batch, index), 0, count, 32
    )
    features = FdEffNetLite0().pooled_features
    classifier = RealImageClassifier(
        features(reconstruct_all(tokenizer, train_batch["tactile"], 64)), train_labels.tolist()
    )
    with torch.no_grad():
        score_NK = torch.stack(
            [
                torch.tensor(classifier.predict(features(decode(tokenizer, codes_NKL[:, k].view(-1, 16, 16)))))
                == labels
                for k in range(codes_NKL.shape[1])
            ],
            1,
        ).float()
    out: dict[str, Any] = {"n": count, "candidates": codes_NKL.shape[1], "guidance": args.guidance}
    out["each_candidate"] = [round(float(v), 4) for v in score_NK.mean(0)]
    out["oracle_best_of_all"] = round(float(score_NK.max(1).values.mean()), 4)
    rows_N = torch.arange(count)
    codebook_KD = codebook_of(tokenizer)
    for data_name, (fit_codes, fit_labels) in fit_sets.items():
        epochs = max(1, round(args.judge_epochs * len(train_codes) / len(fit_codes)))
        for noise in args.judge_noise:
            fits = []
            for seed in args.judge_seeds if args.judge_seeds else [args.seed]:
                clock = time.perf_counter()
                judge_model = fit_code_judge(
                    fit_codes,
                    fit_labels,
                    codebook_KD,
                    num_classes,
                    epochs=epochs,
                    seed=seed,
                    noise=noise,
                    judge=learned_embedding_judge(codebook_KD, num_classes) if args.judge_learned else None,
                )
                with torch.no_grad():
                    real_accuracy = float((judge_model(held_codes).argmax(1) == labels).float().mean())
                    log_p_NK = torch.stack(
                        [
                            judge_model(codes_NKL[:, k].view(-1, 16, 16)).log_softmax(1)[rows_N, labels]
                            for k in range(codes_NKL.shape[1])
                        ],
                        1,
                    )
                entry: dict[str, Any] = {
                    "seed": seed,
                    "fit_grids": len(fit_codes),
                    "epochs": epochs,
                    "train_seconds": round(time.perf_counter() - clock, 1),
                    "held_out_real_code_accuracy": round(real_accuracy, 4),
                    "judge_agrees_with_classifier": round(
                        float(((log_p_NK > math.log(0.5)).float() == score_NK).float().mean()), 4
                    ),
                    "best_of": best_of_groups(log_p_NK, score_NK),
                }
                fits.append(entry)
                print(json.dumps({f"{data_name}_noise_{noise}": entry}), flush=True)
            out[f"{data_name}_noise_{noise}"] = {
                "fits": fits,
                "mean_held_out_real_code_accuracy": round(
                    sum(f["held_out_real_code_accuracy"] for f in fits) / len(fits), 4
                ),
                "mean_best_of_all": round(sum(f["best_of"][codes_NKL.shape[1]] for f in fits) / len(fits), 4),
            }
    return out


# -- rankers: best of K's label rankings, compared on a validation split of the training scenes ---


def best_of_groups(choice_score_NK: torch.Tensor, score_NK: torch.Tensor) -> dict[int, float]:
    """Best of k for k = 1, 2, 4, ... K: the mean of ``score_NK`` at each row's highest
    ``choice_score_NK`` within disjoint groups of k candidates, averaged over the groups."""
    rows_N, count = torch.arange(len(score_NK)), score_NK.shape[1]
    out, group = {}, 1
    while group <= count:
        values = [
            float(score_NK[rows_N, choice_score_NK[:, first : first + group].argmax(1) + first].mean())
            for first in range(0, count - group + 1, group)
        ]
        out[group] = round(sum(values) / len(values), 4)
        group *= 2
    return out


def rankers(args: argparse.Namespace) -> dict[str, Any]:
    """Label rankings for best of K, compared where nothing is tuned on Table 2's scenes: the bundle's
    900 training scenes split into the last ``--n`` (validation conditions) and the rest (what the
    code judges and the evaluation's classifier are fitted on).  ``--candidates`` label samples per
    validation condition (cached in ``--out``.pt), each scored by the evaluation's classifier
    (fitted on the reconstructions of the fitting scenes); then best of k by: the code judge (seeds
    0, 1, 2), the same judges on the candidates re-encoded through the tokenizer (decoded, encoded,
    canonical background), the mean log-probability of five judges (seeds 10-14), and the medoid of
    the candidates by the cosine of their codebook vectors (no class)."""
    from vqtouch.plugins.evaluation.distribution import RealImageClassifier
    from vqtouch.plugins.evaluation.fd_metric import FdEffNetLite0
    from vqtouch.plugins.generator.consensus import medoid_indices
    from vqtouch.plugins.generator.judge import codebook_of, fit_code_judge
    from vqtouch.plugins.tokenizer.loading import reconstruct_all

    host = load_plugins()
    pipe, dataset, train, _, background_3HW = bundle_split(args.bundle, host)
    tokenizer, generator = pipe.tokenizer, pipe.generator.float().eval()
    names = [name.split(":")[-1] for name in pipe.conditioner_names()]
    conditioner = pipe.conditioners[names.index("label")].float().eval()
    batch = dataset.render_batch([train.indices[i] for i in range(len(train))])
    images, labels = batch["tactile"], batch["label"]
    fit = len(train) - args.n
    with torch.no_grad():
        codes, _ = canonical_background(encode(tokenizer, images), tokenizer, background_3HW)
    validation_labels = labels[fit:]
    codes_NKL = cached_candidates(args, host, generator, conditioner, lambda index: labels[index], fit, len(train), 50)
    count, rows_N = codes_NKL.shape[1], torch.arange(args.n)
    features = FdEffNetLite0().pooled_features
    classifier = RealImageClassifier(features(reconstruct_all(tokenizer, images[:fit], 64)), labels[:fit].tolist())
    with torch.no_grad():
        decoded = [decode(tokenizer, codes_NKL[:, k].view(-1, 16, 16)) for k in range(count)]
        reencoded_NKL = torch.stack(
            [
                canonical_background(encode(tokenizer, image), tokenizer, background_3HW)[0].flatten(1)
                for image in decoded
            ],
            1,
        )
    score_NK = torch.stack(
        [torch.tensor(classifier.predict(features(image))) == validation_labels for image in decoded], 1
    ).float()
    out: dict[str, Any] = {
        "validation_conditions": args.n,
        "fitted_on": fit,
        "each_candidate": [round(float(v), 4) for v in score_NK.mean(0)],
        "oracle_best_of_all": round(float(score_NK.max(1).values.mean()), 4),
        "ceiling_reconstructions": round(
            classifier.accuracy(features(reconstruct_all(tokenizer, images[fit:], 64)), validation_labels.tolist()), 4
        ),
    }
    codebook_KD = codebook_of(tokenizer)

    def judge_log_p(seed: int) -> tuple[float, torch.Tensor, torch.Tensor]:
        judge_model = fit_code_judge(codes[:fit], labels[:fit], codebook_KD, len(dataset.class_names), seed=seed)
        with torch.no_grad():
            accuracy = float((judge_model(codes[fit:]).argmax(1) == validation_labels).float().mean())

            def read(grids_NKL: torch.Tensor) -> torch.Tensor:
                return torch.stack(
                    [
                        judge_model(grids_NKL[:, k].view(-1, 16, 16)).log_softmax(1)[rows_N, validation_labels]
                        for k in range(count)
                    ],
                    1,
                )

            return accuracy, read(codes_NKL), read(reencoded_NKL)

    for seed in (0, 1, 2):
        accuracy, on_codes, on_reencoded = judge_log_p(seed)
        out[f"judge_seed{seed}"] = {
            "validation_real_code_accuracy": round(accuracy, 4),
            "codes": best_of_groups(on_codes, score_NK),
            "reencoded": best_of_groups(on_reencoded, score_NK),
        }
        print(json.dumps({f"judge_seed{seed}": out[f"judge_seed{seed}"]}), flush=True)
    ensemble = [judge_log_p(seed) for seed in range(10, 15)]
    out["ensemble_of_5"] = {
        "each_best_of_all": [best_of_groups(log_p, score_NK)[count] for _, log_p, _ in ensemble],
        "mean_log_p": best_of_groups(torch.stack([log_p for _, log_p, _ in ensemble]).mean(0), score_NK),
    }
    latents_NKLD = F.normalize(codebook_KD.cpu()[codes_NKL], dim=-1)
    similarity_NKK = torch.einsum("nkld,njld->nkj", latents_NKLD, latents_NKLD) / codes_NKL.shape[-1]
    medoid = {}
    group = 2
    while group <= count:
        values = []
        for first in range(0, count - group + 1, group):
            block_NKK = similarity_NKK[:, first : first + group, first : first + group]
            chosen_N = medoid_indices(1 - block_NKK) + first
            values.append(float(score_NK[rows_N, chosen_N].mean()))
        medoid[group] = round(sum(values) / len(values), 4)
        group *= 2
    out["medoid_by_codebook_cosine"] = medoid
    return out


# -- cost: what a setting costs per training step ------------------------------------------------


def step_cost(args: argparse.Namespace) -> dict[str, Any]:
    """Seconds per generator training step (batch ``--batch``, the overfit loop's step) for each
    ``--variant`` (``;``-separated ``--set`` overrides, ``""`` for none), interleaved over
    ``--rounds`` rounds of ``--steps`` steps so machine drift hits every variant alike; the median
    round is reported, with its ratio to the first variant."""
    torch.manual_seed(args.seed)
    host = load_plugins()
    tokenizer = load_bundle(args.bundle, host).tokenizer
    dataset, batch = tour_data(host, TOUR_SEED, args.batch)
    codes_BHW = encode(tokenizer, batch["tactile"])
    variants = args.variant or [""]
    models = []
    for variant in variants:
        overrides = [text for text in variant.split(";") if text]
        generator, conditioner, _, _ = build_generator(
            host, tokenizer, args.conditioner, overrides, len(dataset.class_names)
        )
        params = [p for m in (generator, conditioner) for p in m.parameters() if p.requires_grad]
        models.append((generator, conditioner, torch.optim.AdamW(params, lr=1e-5)))
    index = torch.arange(args.batch)

    def one_step(generator: Any, conditioner: Any, optimizer: Any) -> None:
        condition = conditioner(_condition(conditioner, batch, index))
        loss, _ = generator.training_loss(codes_BHW, condition)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()

    for model in models:  # warm-up: first calls allocate
        one_step(*model)
    steps = args.steps or 5
    rounds: list[list[float]] = [[] for _ in variants]
    for _ in range(args.rounds):
        for seconds, model in zip(rounds, models):
            start = time.perf_counter()
            for _ in range(steps):
                one_step(*model)
            seconds.append((time.perf_counter() - start) / steps)
    medians = [sorted(seconds)[len(seconds) // 2] for seconds in rounds]
    return {
        "conditioner": args.conditioner,
        "batch": args.batch,
        "threads": torch.get_num_threads(),
        "seconds_per_step": {variant or "(none)": round(m, 4) for variant, m in zip(variants, medians)},
        "cost_ratio": {variant or "(none)": round(m / medians[0], 2) for variant, m in zip(variants, medians)},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "what",
        choices=[
            "codes",
            "overfit",
            "split",
            "sensitivity",
            "gap",
            "locate",
            "cost",
            "rescore",
            "head",
            "prior",
            "rerank",
            "implicit",
            "judge",
            "rankers",
        ],
    )
    parser.add_argument("--bundle", default="tour")
    parser.add_argument("--conditioner", default="tactile", choices=sorted(CONDITIONERS))
    parser.add_argument("--n", type=int, default=64, help="images or conditions scored")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--pairs", type=int, default=64, help="overfit: training pairs")
    parser.add_argument("--held-out", type=int, default=0, help="overfit: unseen pairs scored after training")
    parser.add_argument("--minutes", type=float, default=5.0)
    parser.add_argument(
        "--steps",
        type=int,
        default=0,
        help="overfit: stop after this many steps (0: time only); cost: per round (0: 5)",
    )
    parser.add_argument("--batch", type=int, default=16)
    parser.add_argument("--lr", type=float, default=4.5e-4)
    parser.add_argument("--warmup", type=int, default=0)
    parser.add_argument(
        "--contact-weight",
        type=float,
        default=0.0,
        help="overfit: generator.model.contact_weight (an auxiliary loss that asks a linear head on the "
        "condition grid's embedding for the contact's cells: codes that are not the no-contact image's); "
        "needs --canonical",
    )
    parser.add_argument("--canonical", action="store_true", help="overfit: train on canonical-background codes")
    parser.add_argument(
        "--pretrain-steps",
        type=int,
        default=0,
        help="overfit: first train the condition grid on the contact loss alone for this many batches, as "
        "generator.train.grid_pretrain does (needs --contact-weight; with --extra-scenes, on that many more "
        "scenes too)",
    )
    parser.add_argument("--sample-steps", type=int, default=25)
    parser.add_argument("--guidance", type=float, default=1.0)
    parser.add_argument(
        "--extra-scenes",
        type=int,
        default=0,
        help="locate, judge, overfit --pretrain-steps: newly rendered training scenes",
    )
    parser.add_argument("--width", type=int, default=32, help="locate: the locator's channels")
    parser.add_argument("--set", action="append", default=[], metavar="model.KEY=V|conditioner.KEY=V")
    parser.add_argument(
        "--variant", action="append", default=[], help="cost: ';'-separated --set overrides of one setting"
    )
    parser.add_argument("--rounds", type=int, default=3, help="cost: interleaved rounds")
    parser.add_argument("--weights", default="", help="rescore: an overfit run's FILE.pt")
    parser.add_argument("--sample-seeds", type=int, nargs="+", default=[1, 2, 3], help="rescore: sampling seeds")
    parser.add_argument("--candidates", type=int, default=8, help="rerank: samples per condition")
    parser.add_argument("--taus", type=float, nargs="+", default=[0.0, 0.1, 0.3], help="prior: thresholds")
    parser.add_argument("--judge-epochs", type=int, default=60, help="judge: epochs of the code judge")
    parser.add_argument("--judge-noise", type=float, nargs="+", default=[0.1], help="judge: random-code shares")
    parser.add_argument(
        "--judge-data",
        nargs="+",
        default=["training"],
        choices=["training", "hflip", "extra"],
        help="judge: what the judge is fitted on (training codes; and mirrored ones; and --extra-scenes new scenes')",
    )
    parser.add_argument("--judge-seeds", type=int, nargs="+", default=[], help="judge: fitting seeds (default --seed)")
    parser.add_argument(
        "--judge-learned", action="store_true", help="judge: trained code embeddings instead of the frozen codebook"
    )
    parser.add_argument("--out", default="")
    args = parser.parse_args()
    commands = {"codes": codes_report, "overfit": overfit, "split": split, "sensitivity": sensitivity, "head": head}
    result = (
        commands
        | {
            "gap": gap,
            "locate": locate,
            "cost": step_cost,
            "rescore": rescore,
            "prior": prior,
            "rerank": rerank,
            "implicit": implicit,
            "judge": judge,
            "rankers": rankers,
        }
    )[args.what](args)
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()

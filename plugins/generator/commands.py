"""``vqtouch train generator``, ``vqtouch generate``, ``vqtouch evaluate generation`` and
``vqtouch tradeoff generator`` (:mod:`.tradeoff`).

``train generator`` runs the scene's stages up to the generator in one run directory (the
tokenizer stage first, unless ``--tokenizer RUN`` names a trained one, whose tokenizer config is
then copied so the generator is built for its codes); ``generate`` writes images from a trained
run through :func:`.pipeline.load_pipeline`.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
from pathlib import Path
from typing import Any

import torch

from vqtouch.core import Assembly, ConfigError, PluginHost, RunDir, atomic_write, hookimpl, run_stage
from vqtouch.core.checkpoint import is_pretrained
from vqtouch.core.cli import (
    add_overwrite_argument,
    add_greyscale_argument,
    add_config_arguments,
    add_run_arguments,
    add_step_argument,
    command_group,
    config_from_args,
    guidance_scale,
    non_negative_int,
    plugin_block,
    positive_int,
    seed_int,
    stage_failure,
    training_run,
    truncation_mass,
)
from vqtouch.plugins.evaluation.feature_networks import feature_size_argument
from vqtouch.core.config import validate_experiment
from vqtouch.core.images import image_grid, save_png
from vqtouch.core.progress import progress
from vqtouch.core.outputs import output_folder, staged_output
from vqtouch.core.runs import interrupted_message, interrupted_status, is_main_process
from vqtouch.plugins.tokenizer import tokenizer_configs, tokenizer_location
from vqtouch.core.data import experiment_split
from vqtouch.core.image_size import image_hw
from vqtouch.plugins.evaluation.contact import dataset_background

from .stage import check_condition_keys
from .best_of import BEST_OF_RANK_HELP, BEST_OF_RANKS, check_best_of, ranks_by_class, refuse_idle_rank


def _with_tokenizer_run(config: Any, tokenizer_run: str, host: PluginHost) -> Any:
    """``config`` set to learn the codes of the tokenizer trained in ``tokenizer_run`` (a run, or a
    tokenizer checkpoint folder such as an adapted tokenizer): its tokenizer section and image
    size, the generator stage alone."""

    source = tokenizer_location(tokenizer_run, host)
    data = config.to_dict()
    if isinstance(source, RunDir):
        trained = source.load_config(host).to_dict()
        data["tokenizer"] = trained["tokenizer"]
        data["data"]["image_size"] = trained["data"]["image_size"]
        path = source.path
    else:
        autoencoder, quantizer, image_size = tokenizer_configs(source)
        data["tokenizer"] |= {"autoencoder": autoencoder, "quantizer": quantizer}
        data["data"]["image_size"] = image_size
        path = source
    data["stages"] = ["generator"]
    data["generator"]["tokenizer_run"] = str(path.resolve())
    return validate_experiment(data, host)


def _train_generator_command(args: argparse.Namespace) -> int:
    host = args.host
    if args.resume and args.tokenizer:
        raise ConfigError("--resume continues a run with its saved config; drop --tokenizer")

    def up_to_the_generator(config: Any) -> Any:
        if "generator" not in config.stages:
            raise ConfigError(f"scene {config.scene!r} has no generator stage; use e.g. --scene label-to-touch")
        if args.tokenizer:
            config = _with_tokenizer_run(config, args.tokenizer, host)
        else:
            stages = config.stages[: config.stages.index("generator") + 1]
            config = validate_experiment({**config.to_dict(), "stages": stages}, host)
        check_condition_keys(config, host)  # before the run folder exists and anything trains
        return config

    run, config = training_run(
        args, host, up_to_the_generator, reads=[("--tokenizer", "tokenizer run", args.tokenizer)], stage="generator"
    )
    assembly = Assembly(config, host)
    with run:
        try:
            for stage in config.stages:
                # On --resume a finished tokenizer stage is not run again: its checkpoint is complete.
                if args.resume and stage == "tokenizer" and (run.path / "eval.json").is_file():
                    continue
                outcome = run_stage(stage, assembly, run, resume=bool(args.resume))
                if outcome.status != "ran":
                    raise stage_failure(outcome)
        except KeyboardInterrupt as exc:
            print(f"\n{interrupted_message(exc, run, 'generator')}", file=sys.stderr)
            return interrupted_status(exc)
    if not is_main_process():
        return 0
    print(json.dumps(json.loads((run.path / "generation.json").read_text()), indent=2))
    print(f"run: {run.path}  (samples.png, generation.json, checkpoints/generator/)")
    return 0


def _condition_arguments(args: argparse.Namespace) -> dict[str, list[str]]:
    given = {key: getattr(args, key) for key in ("label", "visual", "tactile", "text") if getattr(args, key)}
    for item in args.condition:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"--condition {item!r}: expected KEY=VALUE, e.g. --condition material=steel")
        given.setdefault(key, []).append(value)
    for key, values in given.items():
        if any(not value.strip() for value in values):
            example = {"text": "a ball pressed into the gel", "label": "knurl"}.get(key, "FILE")
            raise ConfigError(f"--{key} '': an empty condition; give one, e.g. --{key} {example!r}")
    if len(given) != 1:
        raise ConfigError(
            "give exactly one kind of condition: --label, --visual, --tactile, --text or --condition "
            f"KEY=VALUE (got {', '.join(sorted(given)) or 'none'})"
        )
    return given


#: At most this many samples are drawn into generate's grid.png (all of them are written as files).
GRID_SAMPLES = 64


def _generate_command(args: argparse.Namespace) -> int:
    refuse_idle_rank(args)
    from .pipeline import load_pipeline

    ((key, values),) = _condition_arguments(args).items()
    if len(values) > 1 and args.n_given and len(values) != args.n:
        raise ConfigError(f"{len(values)} --{key} values for --n {args.n}; give one value or --n values")
    # One value per image, or one value for all --n images (never copied --n times: --n may be huge).
    n = args.n if len(values) == 1 else len(values)
    out = Path(args.out)
    images_read = [(f"--{key}", "condition image", value) for value in values if key in ("visual", "tactile")]
    reads = [("--run", "generator run", args.run), *images_read]
    # Staged first: a refused --out (an input, a run, a folder holding files) costs no model loading.
    with staged_output(out, overwrite=args.overwrite, reads=reads) as folder:
        pipe = load_pipeline(args.run, host=args.host, step=args.step, weights=args.weights)
        chosen = pipe.conditioner_index(key, args.conditioner)
        _check_room(out, folder, n, pipe.image_size)
        batches = pipe.batches(
            n,
            **{key: values if len(values) > 1 else values[0]},
            steps=args.steps,
            sampler=args.sampler,
            guidance=args.guidance,
            truncation=args.truncation,
            seed=args.seed,
            batch_size=args.batch_size,
            conditioner=chosen,
            best_of=args.best_of,
            best_of_rank=args.best_of_rank,
        )
        digits = max(4, len(str(n - 1)))
        shown: list[Any] = []
        for start, images in progress(batches, total=-(-n // args.batch_size), desc="generate", unit="batch"):
            for offset, image in enumerate(images):
                save_png(image, folder / f"sample_{start + offset:0{digits}d}.png")
            shown.extend(images[: GRID_SAMPLES - len(shown)])
        save_png(image_grid(torch.stack(shown)), folder / "grid.png")
        settings = {
            "run": str(pipe.run.path.resolve()) if pipe.run is not None else args.run,
            "checkpoint": str(pipe.checkpoint),
            "condition": key,
            "values": values,
            "n": n,
            "grid": f"the first {len(shown)} samples",
            "steps": args.steps or pipe.settings["steps"],
            "sampler": args.sampler or pipe.sampler_name,
            "guidance": pipe.guidance_for(chosen) if args.guidance is None else args.guidance,
            "truncation": pipe.settings["truncation"] if args.truncation is None else args.truncation,
            "weights": pipe.settings["weights"],
            "seed": args.seed,
            "batch_size": args.batch_size,
            "conditioner": pipe.conditioner_names()[chosen],
            "best_of": args.best_of,
            **({"best_of_rank": args.best_of_rank} if args.best_of > 1 else {}),
        }
        text = json.dumps(settings, indent=2) + "\n"
        atomic_write(folder / "generate.json", lambda tmp: tmp.write_text(text, encoding="utf-8"))
    print(f"{n} images -> {out} (sample_*.png, grid.png, generate.json)")
    return 0


def _check_room(out: Path, staged: Path, n: int, image_size: Any) -> None:
    """Refuse ``--n`` samples that cannot fit on the disk ``out`` is staged on (``staged``), before
    generating any."""
    height, width = image_hw(image_size)
    need = n * (3 * height * width + 4096)  # an uncompressed PNG and its file-system overhead: an upper bound
    free = shutil.disk_usage(staged).free
    if need > free:
        raise ConfigError(
            f"--n {n}: the samples need up to {need / 1e9:.3g} GB, but {free / 1e9:.3g} GB are free where --out "
            f"{out} goes; generate fewer, or free space"
        )


def _add_weights_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--weights",
        choices=["ema", "raw"],
        help="sample with the moving average of the weights that training kept (ema) or the raw ones "
        "(default: the run's generator.sample_weights, EMA when the checkpoint holds one)",
    )


#: ``evaluate generation`` flags that only mean something when scoring one run (``--run``).
_RUN_ONLY = ("step", "weights", "conditioner", "steps", "sampler", "guidance", "truncation", "seed", "feature_size")
#: Run-only flags with a default, refused by the experiment only when set to something else.
_RUN_ONLY_DEFAULTS = {"classifier_on": "real"}


def _generation_experiment_command(args: argparse.Namespace) -> int:

    from .experiment import evaluate_generation_experiment

    given = [f"--{name.replace('_', '-')}" for name in _RUN_ONLY if getattr(args, name, None) is not None]
    given += [
        f"--{name.replace('_', '-')}"
        for name, default in _RUN_ONLY_DEFAULTS.items()
        if getattr(args, name, default) != default
    ]
    if given:
        raise ConfigError(
            f"{', '.join(given)} only apply to scoring one run (--run); the experiment (--out) samples "
            "with the scene's generator settings: set them with --set generator.steps=N ..."
        )
    host = args.host
    config = config_from_args(args, host)
    if args.metrics or args.clip_checkpoint or args.clip_architecture:
        config = validate_experiment({**config.to_dict(), "metrics": _metric_blocks(args, config)}, host)
    evaluate_generation_experiment(
        config,
        host,
        Path(args.out),
        seeds=args.seeds,
        n=args.n,
        tokenizer=args.tokenizer,
        overwrite=args.overwrite,
        distribution=args.distribution,
    )
    out = Path(args.out)
    print((out / "generation.md").read_text())
    print(f"-> {out} (generation.json, generation.md, generation.png, seed*/ runs)")
    return 0


def _evaluate_generation_command(args: argparse.Namespace) -> int:
    refuse_idle_rank(args)

    if not args.run and not args.out:
        raise ConfigError(
            "give --run RUN (score a trained generator or pretrained:NAME) or --out DIR (run the experiment)"
        )
    if not args.run:
        return _generation_experiment_command(args)
    if args.overrides or args.config or args.tokenizer or args.overwrite:
        raise ConfigError(
            "--set/--config/--tokenizer/--overwrite belong to the experiment (--out without --run); "
            "scoring a run (--run) uses the run's own config"
        )

    from .pipeline import load_pipeline
    from .stage import baseline_pool, distribution_scorer, held_out_conditions, score_generation

    host = args.host
    if is_pretrained(args.run) and not args.out:
        raise ConfigError(f"--run {args.run}: a bundle is read-only; give --out DIR for its scores")
    if args.clip_checkpoint and not Path(args.clip_checkpoint).expanduser().is_file():
        raise ConfigError(
            f"--clip-checkpoint {args.clip_checkpoint}: no such file; give the open_clip weights file "
            "(.safetensors, .pt or .bin)"
        )
    if not args.out and not os.access(args.run, os.W_OK):  # refused before any sample is drawn
        raise ConfigError(f"--run {args.run} is read-only; give --out DIR for the scores and sample pictures")
    pipe = load_pipeline(args.run, host=host, step=args.step, weights=args.weights)
    config = pipe.config
    assembly = Assembly(config, host)
    dataset = assembly.component("data.dataset")
    train, held_out = experiment_split(dataset, config.data, config.seed)
    names = [item.name for item in config.generator.conditioners]
    if args.conditioner is not None and not 0 <= args.conditioner < len(names):
        raise ConfigError(
            f"--conditioner {args.conditioner}: this generator has conditioners 0..{len(names) - 1} "
            f"({', '.join(names)})"
        )
    out = Path(args.out) if args.out else None
    if out is not None:
        if out.exists() and not out.is_dir():
            raise ConfigError(f"--out {out}: exists and is not a folder")
        output_folder(out)
    # Into --out: every conditioner unless one is named (Table 2's by_conditioner); into the run: one, 0 by default.
    indices = [args.conditioner] if args.conditioner is not None else (list(range(len(names))) if out else [0])
    # A class ranking needs classes: a named conditioner must have them; of all, those that do use it.
    # The consensus ranks every conditioner.
    best_of = {
        index: check_best_of(args.best_of, pipe.conditioners[index], f"{index}:{names[index]}", args.best_of_rank)
        if len(indices) == 1 or args.best_of_rank == "consensus" or ranks_by_class(pipe.conditioners[index])
        else 1
        for index in indices
    }
    sampler_name = args.sampler or pipe.sampler_name
    steps = pipe.check_steps(args.steps or pipe.settings["steps"])
    metrics = [(block["name"], assembly.build("metric", block)) for block in _metric_blocks(args, config)]
    if args.feature_size is not None:
        metrics = [(name, metric) for name, metric in metrics if name != "fd_effnetlite0"]
        metrics.append(
            ("fd_effnetlite0", assembly.build("metric", {"name": "fd_effnetlite0", "image_size": args.feature_size}))
        )
    tag = f"{pipe.checkpoint.name}_{sampler_name}_{steps}"
    background, background_source = dataset_background(train, image_hw(config.data.image_size))
    conditions = held_out_conditions(held_out, dataset, args.n, pipe.device)
    pool = baseline_pool(train)
    scorer = False
    if args.distribution:
        scorer = distribution_scorer(
            conditions,
            pool,
            metrics,
            config.seed,
            tokenizer=pipe.tokenizer if args.classifier_on == "reconstructions" else None,
        )
    folder = out if out is not None else pipe.run.path
    by_conditioner = {}
    for index in indices:
        picture = f"samples_{index}_{names[index]}.png" if out is not None else f"samples_{tag}.png"
        by_conditioner[f"{index}:{names[index]}"] = score_generation(
            generator=pipe.generator,
            conditioner=pipe.conditioners[index],
            tokenizer=pipe.tokenizer,
            sampler=host.build("sampler", sampler_name),
            conditions=conditions,
            pool=pool,
            metrics=metrics,
            background_3HW=background,
            steps=steps,
            guidance=pipe.guidance_for(index) if args.guidance is None else args.guidance,
            truncation=pipe.settings["truncation"] if args.truncation is None else args.truncation,
            seed=config.seed if args.seed is None else args.seed,
            device=pipe.device,
            picture=folder / picture,
            distribution=scorer,
            best_of=best_of[index],
            rank=pipe.best_of_ranking(args.best_of_rank) if best_of[index] > 1 else None,
        )
    head = {
        "checkpoint": str(args.run if is_pretrained(args.run) else pipe.checkpoint),
        "sampler": sampler_name,
        "weights": pipe.settings["weights"],
        "background": background_source,
    }
    if args.distribution:
        head["classifier_trained_on"] = f"the {args.classifier_on} of the training images"
    if out is not None:
        result = head | {"by_conditioner": by_conditioner}
        text = json.dumps(result, indent=2) + "\n"
        atomic_write(out / "generation.json", lambda tmp: Path(tmp).write_text(text))
    else:
        ((name, scores),) = by_conditioner.items()
        result = head | {"conditioner": name, **scores}
        pipe.run.write_json(f"evaluation_generation_{tag}.json", result)
    print(json.dumps(result, indent=2))
    return 0


def _metric_blocks(args: argparse.Namespace, config: Any) -> list[dict[str, Any]]:
    """The metrics ``evaluate generation`` scores, as plugin blocks: ``--metrics`` (comma-separated names, or a
    JSON list of names and ``{"name": ..., options}`` blocks), else the run's own with their options; then
    ``--clip-checkpoint``/``--clip-architecture`` set ``clip_score``'s options, adding it when absent."""
    text = (args.metrics or "").strip()
    if not text:
        blocks = [item.model_dump() for item in config.metrics]
    elif text.startswith("["):
        try:
            items = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ConfigError(f"--metrics is not valid JSON: {exc}") from None
        blocks = [
            plugin_block(json.dumps(item) if isinstance(item, dict) else str(item), "--metrics") for item in items
        ]
    else:
        blocks = [plugin_block(name, "--metrics") for name in text.split(",")]
    clip = {
        key: value
        for key, value in (("checkpoint", args.clip_checkpoint), ("architecture", args.clip_architecture))
        if value
    }
    if clip:
        given = next((block for block in blocks if block["name"] == "clip_score"), {"name": "clip_score"})
        blocks = [block for block in blocks if block["name"] != "clip_score"] + [given | clip]
    return blocks


def _tradeoff_generator_command(args: argparse.Namespace) -> int:
    refuse_idle_rank(args)
    from .tradeoff import tradeoff_command

    return tradeoff_command(args)


def _add_tradeoff_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of ``vqtouch tradeoff generator``."""
    parser.add_argument(
        "--run", required=True, help="a run whose generator stage trained, or a bundle (pretrained:NAME)"
    )
    parser.add_argument("--out", required=True, help="folder for tradeoff.json, tradeoff.md and pareto.png")
    add_overwrite_argument(parser, "tradeoff.json")
    parser.add_argument(
        "--conditioner",
        type=non_negative_int,
        default=0,
        help="which of the generator's conditioners generates (its index; default 0)",
    )
    parser.add_argument("--n", type=positive_int, default=64, help="held-out conditions per setting (at most all)")
    parser.add_argument("--rounds", type=positive_int, default=2, help="interleaved timing rounds (median reported)")
    parser.add_argument("--steps", type=positive_int, nargs="+", default=[100, 50, 25, 10, 5], help="sampling steps")
    parser.add_argument(
        "--samplers",
        nargs="+",
        default=["posterior", "purity", "confidence"],
        help="sampler plugins (the first is the base)",
    )
    parser.add_argument(
        "--guidance",
        type=guidance_scale,
        nargs="+",
        default=[1.0, 3.0],
        help="classifier-free guidance scales (1: unguided; the first is the base)",
    )
    parser.add_argument(
        "--precisions",
        nargs="+",
        default=["fp32", "bf16"],
        metavar="{fp32,bf16}",
        help="fp32, or bf16 autocast (the first is the base)",
    )
    parser.add_argument(
        "--best-of",
        type=positive_int,
        nargs="+",
        metavar="K",
        help="candidates per condition, the --best-of-rank's choice kept (label conditions, or any with "
        "--best-of-rank consensus; the first is the base; default: not a knob, one draw)",
    )
    parser.add_argument(
        "--best-of-rank",
        choices=list(BEST_OF_RANKS),
        default="judge",
        help=BEST_OF_RANK_HELP,
    )
    parser.add_argument(
        "--classifier-on",
        choices=["real", "reconstructions"],
        default="real",
        help="train the classifier-accuracy column's classifier on the real training images (default) or "
        "on the tokenizer's reconstructions of them, which judges decoded images fairly",
    )
    parser.add_argument("--batch-size", type=positive_int, default=16, help="conditions per forward pass")
    parser.add_argument(
        "--grid",
        action="store_true",
        help="every combination (default: one knob at a time around the first sampler, guidance and "
        "precision and the middle --steps value)",
    )
    parser.add_argument("--seed", type=seed_int, help="seed of the sampling draws (default: the run's)")
    # The same option as `vqtouch --threads` (either place; SUPPRESS keeps the global one's value).
    parser.add_argument(
        "--threads", type=positive_int, default=argparse.SUPPRESS, help="torch CPU threads (as vqtouch --threads)"
    )
    _add_distribution_arguments(parser)


def _add_distribution_arguments(parser: argparse.ArgumentParser) -> None:
    """``--distribution/--no-distribution`` and ``--feature-size``, shared by ``evaluate generation``
    and ``tradeoff generator``."""
    parser.add_argument(
        "--distribution",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="also score fd_effnetlite0 against the real held-out images and the accuracy of a "
        "classifier trained on real training images (default: on)",
    )
    parser.add_argument(
        "--feature-size",
        type=feature_size_argument,
        help="side EfficientNet-Lite0 sees the images at (default: the run's fd_effnetlite0 metric's, else 224)",
    )


class _CountAction(argparse.Action):
    """``--n`` that remembers it was given (a single condition value is then repeated)."""

    def __call__(self, parser: Any, namespace: Any, values: Any, option_string: Any = None) -> None:
        setattr(namespace, self.dest, values)
        namespace.n_given = True


@hookimpl
def vqtouch_add_commands(subparsers):
    train = command_group(subparsers, "train", "train a component (tokenizer, ...)")
    generator = train.add_parser(
        "generator",
        help="train a discrete-diffusion generator over a tokenizer's codes "
        "(trains the tokenizer first unless --tokenizer is given)",
    )
    add_config_arguments(generator, default_scene="label-to-touch")
    add_run_arguments(generator)
    generator.add_argument(
        "--tokenizer",
        metavar="RUN",
        help="learn the codes of this tokenizer: a run, a checkpoint folder (e.g. an adapt output) or a bundle "
        "(pretrained:NAME)",
    )
    generator.set_defaults(handler=_train_generator_command)

    evaluate = command_group(subparsers, "evaluate", "evaluate a trained component")
    scored = evaluate.add_parser(
        "generation",
        help="generate the run's held-out conditions and score them against "
        "their ground truth, the no-contact background and the contact "
        "region; with --out, the per-conditioner experiment over seeds "
        "(Table 2: JSON, markdown, PNG)",
    )
    scored.add_argument(
        "--run",
        help="a run whose generator stage trained, or a bundle (pretrained:NAME): score it "
        "(with --out DIR, into DIR/generation.json; a bundle is read-only and needs "
        "--out)",
    )
    scored.add_argument(
        "--out",
        help="without --run: run the experiment into this folder: train the scene's "
        "generator once per seed over one tokenizer and score every conditioner against "
        "the baselines; with --run: where the run's scores go",
    )
    scored.add_argument(
        "--seeds", type=seed_int, nargs="+", default=[0, 1, 2], help="with --out: generator seeds (default 0 1 2)"
    )
    scored.add_argument(
        "--tokenizer",
        metavar="RUN",
        help="with --out: the trained tokenizer every seed's generator "
        "learns (default: the scene's, trained once into OUT/tokenizer)",
    )
    scored.add_argument(
        "--overwrite", action="store_true", help="with --out: run again into a folder that holds an earlier result"
    )
    add_config_arguments(scored, default_scene="tour")
    add_step_argument(scored)
    _add_weights_argument(scored)
    scored.add_argument(
        "--conditioner", type=non_negative_int, help="which of the generator's conditioners (index; default 0)"
    )
    scored.add_argument("--n", type=positive_int, default=64, help="held-out conditions to generate (at most all)")
    scored.add_argument("--steps", type=positive_int, help="sampling steps (default: the run's generator.steps)")
    scored.add_argument("--sampler", help="sampler plugin (default: the run's generator.sampler)")
    scored.add_argument(
        "--guidance",
        type=guidance_scale,
        help="classifier-free guidance scale (1: none; default: the run's for the conditioner)",
    )
    scored.add_argument(
        "--truncation", type=truncation_mass, help="keep the most likely codes holding this mass (1: all)"
    )
    scored.add_argument("--seed", type=seed_int, help="seed of the sampling draws (default: the run's)")
    scored.add_argument(
        "--metrics",
        help="comma-separated metric plugins, or a JSON list of names and "
        '{"name": ..., options} blocks (default: the run\'s metrics)',
    )
    scored.add_argument(
        "--clip-checkpoint",
        metavar="PATH",
        help="open_clip weights file of the clip_score metric (CLIP-space agreement of each "
        "generated image with its condition), added to the metrics; a clip_score listed "
        "without it reads VQTOUCH_CLIP_CKPT or VQTOUCH_WEIGHTS_DIR, else is reported as skipped",
    )
    scored.add_argument(
        "--clip-architecture",
        metavar="NAME",
        help="open_clip model name the --clip-checkpoint file holds (default: ViT-B-32)",
    )
    _add_distribution_arguments(scored)
    scored.add_argument(
        "--best-of",
        type=positive_int,
        default=1,
        metavar="K",
        help="draw K candidates per condition and keep --best-of-rank's choice (about K times the time of one "
        "draw; 1: plain sampling); with every conditioner scored and a class ranking, conditioners without "
        "classes draw once",
    )
    scored.add_argument(
        "--best-of-rank",
        choices=list(BEST_OF_RANKS),
        default="judge",
        help=BEST_OF_RANK_HELP,
    )
    scored.add_argument(
        "--classifier-on",
        choices=["real", "reconstructions"],
        default="real",
        help="with --run: train the distribution scores' classifier on the real training images "
        "(default) or on the tokenizer's reconstructions of them, which judges decoded images "
        "(samples and the tokenizer's ceiling) fairly",
    )
    scored.set_defaults(handler=_evaluate_generation_command)

    tradeoff = command_group(subparsers, "tradeoff", "measure the speed/quality trade-off of a trained component")
    traded = tradeoff.add_parser(
        "generator",
        help="time and score a trained generator at each sampler, steps, "
        "guidance and precision setting (tradeoff.json, tradeoff.md, "
        "pareto.png)",
    )
    _add_tradeoff_arguments(traded)
    add_step_argument(traded)
    traded.set_defaults(handler=_tradeoff_generator_command)

    generate = subparsers.add_parser("generate", help="generate tactile images with a trained generator run")
    generate.add_argument(
        "--run", required=True, help="a run whose generator stage trained, or a bundle (pretrained:NAME)"
    )
    add_step_argument(generate)
    _add_weights_argument(generate)
    generate.add_argument("--label", action="append", help="class index or name (repeatable: one per image)")
    generate.add_argument("--visual", action="append", metavar="IMG", help="visual image file (repeatable)")
    generate.add_argument("--tactile", action="append", metavar="IMG", help="conditioning tactile image (repeatable)")
    generate.add_argument("--text", action="append", help="text description (repeatable)")
    generate.add_argument(
        "--condition",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a condition a third-party conditioner reads (sample key = value)",
    )
    generate.add_argument(
        "--conditioner",
        metavar="INDEX|NAME",
        help="which of the generator's conditioners encodes the condition (index or name, e.g. "
        "1 or visual); needed only when several read the same kind of condition",
    )
    generate.add_argument(
        "--n",
        type=positive_int,
        default=1,
        action=_CountAction,
        help="number of images (a single condition value is repeated)",
    )
    generate.add_argument("--steps", type=positive_int, help="sampling steps (default: the run's generator.steps)")
    generate.add_argument("--sampler", help="sampler plugin (default: the run's generator.sampler)")
    generate.add_argument(
        "--guidance",
        type=guidance_scale,
        help="classifier-free guidance scale (1: none; default: the run's for the conditioner)",
    )
    generate.add_argument(
        "--truncation", type=truncation_mass, help="keep the most likely codes holding this mass (1: all)"
    )
    generate.add_argument("--seed", type=seed_int, default=0, help="seed: same seed and settings, same images")
    generate.add_argument("--batch-size", type=positive_int, default=16, help="images per forward pass")
    generate.add_argument(
        "--best-of",
        type=positive_int,
        default=1,
        metavar="K",
        help="draw K candidates per image and keep --best-of-rank's choice (a label condition, or any with "
        "--best-of-rank consensus; about K times the time of one draw; default 1: plain sampling)",
    )
    generate.add_argument(
        "--best-of-rank",
        choices=list(BEST_OF_RANKS),
        default="judge",
        help=BEST_OF_RANK_HELP,
    )
    generate.add_argument(
        "--out", required=True, help="folder for sample_*.png, grid.png and generate.json (written whole, at the end)"
    )
    generate.add_argument("--overwrite", action="store_true", help="replace what --out holds")
    add_greyscale_argument(generate)
    generate.set_defaults(handler=_generate_command, n_given=False)

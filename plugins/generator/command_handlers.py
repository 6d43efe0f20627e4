"""The generator commands' handlers (their parsers are in commands.py): ``vqtouch train generator``,
``vqtouch generate``, ``vqtouch evaluate generation`` and ``vqtouch tradeoff generator`` (:mod:`.tradeoff`)."""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
from pathlib import Path
from typing import Any

import torch

from vqtouch.core import Assembly, ConfigError, PluginHost, atomic_write
from vqtouch.plugins.runtime.execution import run_stage
from vqtouch.plugins.runtime.interruptions import interrupted_message, interrupted_status
from vqtouch.plugins.runtime.run_dir import RunDir, is_main_process
from vqtouch.core.checkpoint import is_pretrained
from vqtouch.plugins.cli.app import (
    config_from_args,
    plugin_block,
    stage_failure,
    training_run,
)
from vqtouch.core.config import validate_experiment
from vqtouch.plugins.utils.images import image_grid, save_png
from vqtouch.plugins.utils.progress import progress
from vqtouch.plugins.runtime.outputs import output_folder, staged_output
from vqtouch.plugins.tokenizer import tokenizer_configs, tokenizer_location
from vqtouch.plugins.utils.splits import experiment_split
from vqtouch.core.image_size import image_hw
from vqtouch.plugins.evaluation.contact import dataset_background

from .stage import check_condition_keys
from .best_of import check_best_of, ranks_by_class, refuse_idle_rank


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


def cmd_train_generator(args: argparse.Namespace) -> int:
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


def cmd_generate(args: argparse.Namespace) -> int:
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


def cmd_evaluate_generation(args: argparse.Namespace) -> int:
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
    from .scoring import baseline_pool, held_out_conditions

    _refuse_before_loading(args)
    pipe = load_pipeline(args.run, host=args.host, step=args.step, weights=args.weights)
    config = pipe.config
    assembly = Assembly(config, args.host)
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
    best_of = _best_of_by_conditioner(args, pipe, names, out)
    sampler_name = args.sampler or pipe.sampler_name
    steps = pipe.check_steps(args.steps or pipe.settings["steps"])
    metrics = _scoring_metrics(args, assembly, config)
    tag = f"{pipe.checkpoint.name}_{sampler_name}_{steps}"
    background, background_source = dataset_background(train, image_hw(config.data.image_size))
    conditions = held_out_conditions(held_out, dataset, args.n, pipe.device)
    pool = baseline_pool(train)
    by_conditioner = _score_conditioners(
        args,
        pipe,
        names,
        best_of,
        sampler_name,
        out,
        tag,
        conditions=conditions,
        pool=pool,
        metrics=metrics,
        background_3HW=background,
        steps=steps,
        device=pipe.device,
        distribution=_run_distribution_scorer(args, pipe, conditions, pool, metrics),
    )
    _report_scores(args, pipe, out, tag, sampler_name, background_source, by_conditioner)
    return 0


def _refuse_before_loading(args: argparse.Namespace) -> None:
    """Refuse, before any model is loaded, scores with nowhere to go and a CLIP checkpoint that is not there."""
    if is_pretrained(args.run) and not args.out:
        raise ConfigError(f"--run {args.run}: a bundle is read-only; give --out DIR for its scores")
    if args.clip_checkpoint and not Path(args.clip_checkpoint).expanduser().is_file():
        raise ConfigError(
            f"--clip-checkpoint {args.clip_checkpoint}: no such file; give the open_clip weights file "
            "(.safetensors, .pt or .bin)"
        )
    if not args.out and not os.access(args.run, os.W_OK):  # refused before any sample is drawn
        raise ConfigError(f"--run {args.run} is read-only; give --out DIR for the scores and sample pictures")


def _best_of_by_conditioner(args: argparse.Namespace, pipe: Any, names: list[str], out: Path | None) -> dict[int, int]:
    """The conditioners scored, in order, each with the candidates it draws per condition."""
    # Into --out: every conditioner unless one is named (Table 2's by_conditioner); into the run: one, 0 by default.
    indices = [args.conditioner] if args.conditioner is not None else (list(range(len(names))) if out else [0])
    # A ranker by class needs classes: a named conditioner must have them; of all, those that do use it.
    # A ranker that reads no classes (the consensus) ranks every conditioner.
    ranker = pipe.best_of_ranker(args.best_of_rank)
    return {
        index: check_best_of(args.best_of, pipe.conditioners[index], f"{index}:{names[index]}", ranker)
        if len(indices) == 1 or not ranker.needs_classes or ranks_by_class(pipe.conditioners[index])
        else 1
        for index in indices
    }


def _scoring_metrics(args: argparse.Namespace, assembly: Any, config: Any) -> list[tuple[str, Any]]:
    """The metrics built from :func:`_metric_blocks`, ``fd_effnetlite0`` at ``--feature-size`` when given."""
    metrics = [(block["name"], assembly.build("metric", block)) for block in _metric_blocks(args, config)]
    if args.feature_size is not None:
        metrics = [(name, metric) for name, metric in metrics if name != "fd_effnetlite0"]
        metrics.append(
            ("fd_effnetlite0", assembly.build("metric", {"name": "fd_effnetlite0", "image_size": args.feature_size}))
        )
    return metrics


def _run_distribution_scorer(
    args: argparse.Namespace, pipe: Any, conditions: Any, pool: list[dict[str, Any]], metrics: list[tuple[str, Any]]
) -> Any:
    """With ``--distribution``, the scorer every conditioner shares (classifier per ``--classifier-on``), else False."""
    from .scoring import distribution_scorer

    if not args.distribution:
        return False
    return distribution_scorer(
        conditions,
        pool,
        metrics,
        pipe.config.seed,
        tokenizer=pipe.tokenizer if args.classifier_on == "reconstructions" else None,
    )


def _score_conditioners(
    args: argparse.Namespace,
    pipe: Any,
    names: list[str],
    best_of: dict[int, int],
    sampler_name: str,
    out: Path | None,
    tag: str,
    **common: Any,
) -> dict[str, dict[str, Any]]:
    """:func:`.scoring.score_generation` of each conditioner of ``best_of``, by ``index:name``."""
    from .scoring import score_generation

    folder = out if out is not None else pipe.run.path
    by_conditioner = {}
    for index, draws in best_of.items():
        picture = f"samples_{index}_{names[index]}.png" if out is not None else f"samples_{tag}.png"
        by_conditioner[f"{index}:{names[index]}"] = score_generation(
            generator=pipe.generator,
            conditioner=pipe.conditioners[index],
            tokenizer=pipe.tokenizer,
            sampler=args.host.build("sampler", sampler_name),
            **common,
            guidance=pipe.guidance_for(index) if args.guidance is None else args.guidance,
            truncation=pipe.settings["truncation"] if args.truncation is None else args.truncation,
            seed=pipe.config.seed if args.seed is None else args.seed,
            picture=folder / picture,
            best_of=draws,
            rank=pipe.best_of_ranking(args.best_of_rank) if draws > 1 else None,
            precision=pipe.sample_precision,
        )
    return by_conditioner


def _report_scores(
    args: argparse.Namespace,
    pipe: Any,
    out: Path | None,
    tag: str,
    sampler_name: str,
    background_source: Any,
    by_conditioner: dict[str, dict[str, Any]],
) -> None:
    """Write the scores (``out``/generation.json, else the run's evaluation_generation_<tag>.json) and print them."""
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


def cmd_tradeoff_generator(args: argparse.Namespace) -> int:
    refuse_idle_rank(args)
    from .tradeoff import tradeoff_command

    return tradeoff_command(args)

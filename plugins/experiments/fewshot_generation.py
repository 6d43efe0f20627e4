"""``vqtouch fewshot``: from an unseen sensor's images to generated images of that sensor.

::

    vqtouch fewshot --run FAMILY_RUN --images DIR --out OUT [--shots 50] [--ratio 5] \\
        [--tokenizer-steps 200] [--generator-steps 300] [--families DIR] [--samples 32] [--seed 0]

``FAMILY_RUN`` is a generator run of the sensor family (its tokenizer, generator, conditioners and
data), or a bundle (``pretrained:tour``: its recorded config names its data, rendered here).
``--images`` is a folder of the unseen sensor's images (any layout ``vqtouch adapt`` reads) or a
registered sensor (name or JSON variant), which renders them.  Five steps, one line each:

1. **assign and adapt the tokenizer** (``vqtouch adapt``): the shots are assigned to a sensor
   family (refused, in one line, when they match none; ``--family K`` forces one) and the family
   run's tokenizer is fine-tuned on them mixed 1:``ratio`` with the family's members -> ``OUT/tokenizer``;
2. **fine-tune the generator**: the family generator learns the adapted tokenizer's codes of
   ``ratio`` family training samples per shot (their conditions) and of the shots (no condition),
   with a sensor tag that tells the two apart (:func:`vqtouch.plugins.generator.fine_tune_for_sensor`)
   -> ``OUT/generator``, a generator run that ``vqtouch generate`` reads;
3. **sample every condition** the family generator has (the family's held-out conditions), in the
   new sensor's appearance -> ``OUT/samples_<i>_<name>.png``: condition (when it is an image) |
   generated new-sensor image | the zero-shot family generator's | a real image of the new sensor;
4. **score** on the new sensor's held-out images (never the shots): ``fd_effnetlite0`` of each
   conditioner's samples beside the zero-shot family generator (its own tokenizer, no adaptation),
   the shots themselves (copying real images of the sensor) and the sensor's no-contact background
   (drawing nothing); ``--ratio 0`` is the shots-alone arm;
5. **write** ``OUT/fewshot.json`` and ``OUT/fewshot.md``.

``OUT`` is written whole at the end (staged beside it): a failed run leaves nothing half-written.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
from pathlib import Path
from typing import Any, Sequence

import torch

from vqtouch.core import Assembly, ConfigError, PluginHost, StageJob, StageUnavailable
from vqtouch.plugins.data.sensor_folders import folder_of
from vqtouch.plugins.runtime.interruptions import interrupted_status
from vqtouch.plugins.runtime.run_dir import RunDir
from vqtouch.core.checkpoint import is_pretrained
from vqtouch.plugins.utils.splits import experiment_split
from vqtouch.plugins.utils.files import read_model
from vqtouch.plugins.runtime.outputs import staged_output
from vqtouch.plugins.evaluation.records import markdown_table, provenance

from .fewshot_generation_plugin import FEWSHOT_FOLDER, FEWSHOT_OPTIONS, FewshotSection  # noqa: F401 (their old home)
from .fewshot_scoring import CLASSIFIER_TEXT, SCORE_HEADERS, SCORE_KEYS, sample_and_score

#: What ``fewshot.json`` keeps of the tokenizer's adaptation.
ADAPT_KEYS = ("target", "family", "assignment", "steps", "held_out", "before", "after")


@dataclasses.dataclass(frozen=True)
class _FewshotSettings:
    """The settings of one :func:`fewshot_generation` run beside its family run, images and output
    (the ratio resolved)."""

    shots: int
    ratio: float
    tokenizer_steps: int
    tokenizer_part: str
    rebase: bool
    generator_steps: int
    families: str | None
    family: int | None
    threshold: float | None
    samples: int
    eval_images: int
    seed: int
    feature_size: int
    score: bool


def _family_tokenizer(family_run: str, host: PluginHost) -> tuple[Any, Path]:
    """The tokenizer the family generator was trained on (what is adapted) and its checkpoint folder:
    a bundle's own, or the one a run's generator product records."""
    from vqtouch.plugins.generator import generator_tokenizer
    from vqtouch.plugins.tokenizer import load_tokenizer

    if is_pretrained(family_run):
        return load_tokenizer(family_run, host)
    run = RunDir.open(family_run)
    config = run.load_config(host)
    if getattr(config, "generator", None) is None or config.generator.model is None:
        raise ConfigError(
            f"--run {family_run}: its config has no generator; give a family's generator run "
            "(`vqtouch train generator`) or a bundle (pretrained:NAME)"
        )
    return load_tokenizer(generator_tokenizer(run, config.generator), host)


def adapted_summary(
    adapted: Path, folder: Path, part: str | None = None, rebase: bool | None = None
) -> dict[str, Any] | None:
    """``adapted``'s ``adapt.json`` when it was adapted from the tokenizer in ``folder`` (and, given
    ``part`` and ``rebase``, adapting that part, re-based or not), else None: only such a tokenizer can
    stand in for adapting again."""
    from vqtouch.plugins.adaptation import AdaptRecord

    made = read_model(adapted / "adapt.json", AdaptRecord).model_dump()
    if Path(made["adapted_from"]).resolve() != folder.resolve():
        return None
    if rebase is not None and made["rebase"] != rebase:
        return None
    return made if part is None or made.get("part", "all") == part else None


def family_background(config: Any, host: PluginHost) -> torch.Tensor | None:
    """The no-contact image of the family generator's training data (what its canonical background codes
    decode to): the one a re-based sensor's images are moved onto."""
    from vqtouch.core.image_size import image_hw
    from vqtouch.plugins.evaluation.contact import dataset_background

    dataset = Assembly(config, host).component("data.dataset")
    train, _ = experiment_split(dataset, config.data, config.seed)
    background, _ = dataset_background(train, image_hw(config.data.image_size))
    return background


def new_sensor_images(
    images: str, host: PluginHost, *, shots: int, eval_images: int, image_size: Any, seed: int
) -> tuple[str, torch.Tensor, torch.Tensor, torch.Tensor, str]:
    """The unseen sensor's name, shots, held-out images, no-contact background and how it was made,
    exactly as ``vqtouch adapt`` draws them for ``seed``."""
    from vqtouch.plugins.adaptation import sensor_background, target_images

    name, _, shots_N3HW, held_out_M3HW = target_images(
        images, host, shots=shots, eval_images=eval_images, image_size=image_size, seed=seed
    )
    background_3HW, source = sensor_background(images, host, image_size)
    return name, shots_N3HW, held_out_M3HW, background_3HW, source


def fewshot_generation(
    family_run: str,
    images: str,
    out: Path,
    host: PluginHost,
    *,
    shots: int = 50,
    ratio: float | None = None,
    tokenizer_steps: int = 200,
    tokenizer_part: str = "decoder",
    rebase: bool = True,
    generator_steps: int = 300,
    families: str | None = None,
    family: int | None = None,
    threshold: float | None = None,
    samples: int = 32,
    eval_images: int = 64,
    seed: int = 0,
    feature_size: int = 224,
    score: bool = True,
    adapted: Path | None = None,
    overwrite: bool = False,
    argv: Sequence[str] | None = None,
    report: Any = print,
) -> dict[str, Any]:
    """Run the five steps of the module docstring; returns what ``fewshot.json`` holds.  ``adapted``: a
    tokenizer ``vqtouch adapt`` already adapted from the family's to ``images`` with these ``shots``,
    ``ratio`` and ``seed`` (the ``adapt`` stage's), copied instead of adapting again.  ``ratio``: family
    images per shot (default ``vqtouch adapt``'s).  ``rebase``: adapt a re-based tokenizer
    (:attr:`vqtouch.plugins.adaptation.AdaptSettings.rebase`) onto :func:`family_background`."""
    from vqtouch.plugins.generator import check_condition_keys, load_pipeline

    settings = _FewshotSettings(
        shots=shots,
        ratio=_checked_ratio(ratio),
        tokenizer_steps=tokenizer_steps,
        tokenizer_part=tokenizer_part,
        rebase=rebase,
        generator_steps=generator_steps,
        families=families,
        family=family,
        threshold=threshold,
        samples=samples,
        eval_images=eval_images,
        seed=seed,
        feature_size=feature_size,
        score=score,
    )
    out = Path(out)
    tokenizer, folder = _family_tokenizer(family_run, host)
    adapted = None if adapted is None else Path(adapted)
    reused = None if adapted is None else _reusable_adapted(adapted, folder, family_run, rebase)
    family_pipe = load_pipeline(family_run, host=host)
    # The family data the fine-tuning reads, before anything is written.
    check_condition_keys(family_pipe.config, host, family_pipe.conditioners)
    result: dict[str, Any] = {
        "family_run": str(family_run),
        "images": images,
        "shots": shots,
        "ratio": settings.ratio,
        "seed": seed,
    }
    with staged_output(out, overwrite=overwrite, reads=_reads(family_run, images, families)) as partial:
        if adapted is not None:
            report(f"1/5 reuse the tokenizer adapted in {adapted}")
            shutil.copytree(adapted, partial / "tokenizer")
            summary = reused
        else:
            summary = _adapt(tokenizer, folder, images, host, partial, family_pipe.config, settings, report)
        result["adapt"] = {key: summary[key] for key in ADAPT_KEYS if key in summary}
        result |= _fine_tune_and_sample(family_run, images, out, partial, host, family_pipe, settings, argv, report)
        report("5/5 write fewshot.json and fewshot.md")
        record = {**result, "provenance": provenance()}
        (partial / "fewshot.json").write_text(json.dumps(record, indent=2, default=str) + "\n")
        (partial / "fewshot.md").write_text("\n".join(render_markdown(result)) + "\n")
    return result


def _checked_ratio(ratio: float | None) -> float:
    """``ratio``, ``vqtouch adapt``'s default when None; a one-line ConfigError when negative."""
    from vqtouch.plugins.adaptation import AdaptSettings

    ratio = AdaptSettings.ratio if ratio is None else ratio
    if ratio < 0:
        raise ConfigError(f"--ratio {ratio}: family images per shot must be >= 0 (0: the shots alone)")
    return ratio


def _reusable_adapted(adapted: Path, folder: Path, family_run: str, rebase: bool) -> dict[str, Any]:
    """``adapted``'s ``adapt.json`` summary; a one-line ConfigError unless it was adapted from the
    family tokenizer in ``folder``, re-based as ``rebase`` says."""
    reused = adapted_summary(adapted, folder, rebase=rebase)
    if reused is None:
        raise ConfigError(
            f"{adapted} was not adapted from {folder}, the tokenizer of {family_run}'s generator,"
            f"{'' if rebase else ', not'} re-based; adapt that one (leave the adapted tokenizer out)"
        )
    return reused


def _reads(family_run: str, images: str, families: str | None) -> list[tuple[str, str, Any]]:
    """What the run reads (option, what it is, path), which ``--out`` must not hold."""
    reads: list[tuple[str, str, Any]] = [("--images", "images", images)] if folder_of(images) is not None else []
    if not is_pretrained(family_run):  # what it reads of the run: the fewshot stage writes beside them
        reads += [("--run", "family run", Path(family_run) / name) for name in ("checkpoints", "config.json")]
    if families is not None:
        reads.append(("--families", "sensor families", families))
    return reads


def _adapt(
    tokenizer: Any,
    folder: Path,
    images: str,
    host: PluginHost,
    partial: Path,
    config: Any,
    settings: _FewshotSettings,
    report: Any,
) -> dict[str, Any]:
    """Step 1: the shots assigned to a sensor family and the family ``tokenizer`` adapted to them
    into ``partial/tokenizer``; its summary."""
    from vqtouch.plugins.adaptation import AdaptSettings, adapt_tokenizer, families_to_adapt_from, registered_source

    report(f"1/5 assign and adapt the tokenizer of {folder} ({settings.tokenizer_steps} steps)")
    if settings.families is None:
        report("    no --families: clustering the registered sensor families and 3 variants of each")
    fitted = families_to_adapt_from(
        tokenizer,
        folder,
        host,
        families=Path(settings.families) if settings.families else None,
        where=f"the families in {settings.families}",
        exclude=registered_source(images),
        seed=settings.seed,
    )
    adapt_settings = AdaptSettings(
        shots=settings.shots,
        ratio=settings.ratio,
        steps=settings.tokenizer_steps,
        eval_images=settings.eval_images,
        threshold=settings.threshold,
        family=settings.family,
        seed=settings.seed,
        part=settings.tokenizer_part,
        rebase=settings.rebase,
    )
    return adapt_tokenizer(
        str(folder),
        images,
        fitted,
        host,
        partial / "tokenizer",
        adapt_settings,
        report=lambda line: report(f"    {line}"),
        family_background_3HW=family_background(config, host) if settings.rebase else None,
    )


def _fine_tune_and_sample(
    family_run: str,
    images: str,
    out: Path,
    partial: Path,
    host: PluginHost,
    family_pipe: Any,
    settings: _FewshotSettings,
    argv: Sequence[str] | None,
    report: Any,
) -> dict[str, Any]:
    """Steps 2 to 4 on the adapted tokenizer in ``partial``: the family generator fine-tuned into
    ``partial/generator``, every condition sampled and scored; the ``fine_tune``, sampling, ``scores``
    and ``background`` entries of ``fewshot.json``."""
    from vqtouch.plugins.generator import fine_tune_for_sensor, load_pipeline

    config = family_pipe.config
    name, shots_N3HW, held_out_M3HW, background_3HW, background_source = new_sensor_images(
        images,
        host,
        shots=settings.shots,
        eval_images=settings.eval_images,
        image_size=config.data.image_size,
        seed=settings.seed,
    )
    report(
        f"2/5 fine-tune the family generator on {settings.shots} shots and {settings.ratio:g} family samples per shot"
    )
    family_sensor = config.sensor.name if getattr(config, "sensor", None) is not None else "family"
    tuned = fine_tune_for_sensor(
        family_run,
        partial / "tokenizer",
        shots_N3HW,
        background_3HW,
        partial / "generator",
        host,
        ratio=settings.ratio,
        steps=settings.generator_steps,
        seed=settings.seed,
        sensor_names=(family_sensor, name),
        argv=argv,
        report=lambda line: report(f"    {line}"),
    )
    tuned["tokenizer"] = str((out / "tokenizer").resolve())  # where it is once moved into place
    sampled = sample_and_score(
        load_pipeline(partial / "generator", host=host),
        family_pipe,
        images,
        name,
        partial,
        host,
        held_out_M3HW=held_out_M3HW,
        shots_N3HW=shots_N3HW,
        background_3HW=background_3HW,
        samples=settings.samples,
        seed=settings.seed,
        feature_size=settings.feature_size,
        score=settings.score,
        report=report,
    )
    return {"fine_tune": tuned, **sampled, "background": background_source}


def render_markdown(result: dict[str, Any]) -> list[str]:
    """``fewshot.md``: what was adapted and fine-tuned, and the scores table."""
    tune = result["fine_tune"]
    adapt = result.get("adapt", {})
    lines = [
        f"# Few-shot generation: {adapt.get('target', result['images'])}",
        "",
        f"Family run `{result['family_run']}`; {result['shots']} shots, {tune['family_samples']} family "
        f"samples (ratio {result['ratio']:g}); generator fine-tuned {tune['steps']} steps in {tune['seconds']:.0f} s.",
    ]
    if "before" in adapt and "after" in adapt:
        lines.append(
            f"Adapted tokenizer on {adapt.get('held_out', '?')} held-out images: PSNR {adapt['before']['psnr']:.2f} -> "
            f"{adapt['after']['psnr']:.2f} dB."
        )
    lines += ["", f"Samples: {', '.join(result['samples']['pictures'])} ({result['samples']['rows']}).", ""]
    if result["scores"]:
        lines += [
            f"fd_effnetlite0 (lower is better) of {result['samples']['count']} images per arm against as many "
            "held-out images of the new sensor (never the shots)"
            + (
                f"; contact PSNR against its image of each condition's own contact; {CLASSIFIER_TEXT}"
                if result.get("classifier", {}).get("train_images")
                else ":"
            ),
            "",
            *markdown_table(result["scores"], ["conditioner", "arm"], list(SCORE_KEYS), SCORE_HEADERS),
        ]
    lines += ["", f"No-contact background: {result['background']}."]
    return lines


def _run_fewshot(args: argparse.Namespace, out: Path) -> dict[str, Any]:
    return fewshot_generation(
        args.run,
        args.images,
        out,
        args.host,
        ratio=args.ratio,
        seed=args.seed,
        score=not args.no_score,
        **fewshot_options(args),
        overwrite=args.overwrite,
        argv=args.argv,
        report=lambda line: print(line, flush=True),
    )


def _fewshot_command(args: argparse.Namespace) -> int:
    out = Path(args.out)
    try:
        result = _run_fewshot(args, out)
    except KeyboardInterrupt as exc:  # Ctrl-C, SIGTERM, or either during the fine-tuning
        cause = getattr(exc, "cause", None) or ("SIGTERM" if getattr(exc, "signum", None) else "Ctrl-C")
        print(
            f"vqtouch: fewshot stopped by {cause}; nothing of this run is kept (--out {out} is written whole once "
            "all five steps finish, and holds what it held before): run the command again",
            file=sys.stderr,
        )
        return interrupted_status(exc)
    print((out / "fewshot.md").read_text())
    pictures = ", ".join(result["samples"]["pictures"])
    print(f"-> {out} (tokenizer/, generator/ (vqtouch generate --run {out / 'generator'}), {pictures}, fewshot.json)")
    return 0


def fewshot_options(args: argparse.Namespace) -> dict[str, Any]:
    """The :func:`fewshot_generation` options the commands share, from their parsed ``args``."""
    return {name: getattr(args, name) for name in FEWSHOT_OPTIONS}


def run_fewshot_stage(job: StageJob) -> dict[str, Any]:
    """Generate images of the target sensor from its shots (:func:`fewshot_generation`) into ``<run>/fewshot``."""
    section, config = job.section, job.config
    adapt = config.adapt
    family_run = section.family_generator or str(job.run.path)
    if not is_pretrained(family_run) and "generator" not in job.run.products():
        raise StageUnavailable(
            "no generator in this run; run the generator stage first or set fewshot.family_generator"
        )
    target = job.assembly.sensor_config("target")
    images = json.dumps({"name": target.name, **target.model_dump(mode="json", exclude_defaults=True)}, sort_keys=True)
    adapted = job.run.products().get("adapted_tokenizer")
    reuse = None
    if adapted is not None:
        _, folder = _family_tokenizer(family_run, job.host)
        if adapted_summary(adapted.path, folder, section.tokenizer_part, section.rebase) is not None:
            reuse = adapted.path
    result = fewshot_generation(
        family_run,
        images,
        job.run.path / FEWSHOT_FOLDER,
        job.host,
        shots=adapt.shots,
        ratio=adapt.ratio,
        tokenizer_steps=adapt.steps,
        tokenizer_part=section.tokenizer_part,
        rebase=section.rebase,
        generator_steps=section.generator_steps,
        threshold=adapt.threshold,
        family=adapt.family,
        samples=section.samples,
        eval_images=adapt.eval_images,
        seed=config.seed,
        feature_size=section.feature_size,
        score=section.score,
        adapted=reuse,
        overwrite=True,
        report=lambda line: None,
    )
    job.publish("fewshot_generator", f"{FEWSHOT_FOLDER}/generator", target=result["adapt"].get("target", ""))
    summary = _stage_summary(result, family_run, reuse is not None)
    names = ", ".join(label.split(":", 1)[1] for label in result["conditioners"])
    return {
        **summary,
        "picture": f"{FEWSHOT_FOLDER}/samples.png",
        "caption": (
            f"Images of the unseen sensor {summary['target']} generated from the family generator fine-tuned on "
            f"{summary['shots']} of its images: for each condition ({names}), "
            "the condition when it is an image, then the generated images; the last row is real images of the "
            "sensor (held out). Per-condition pictures beside the zero-shot generator's are in fewshot/."
        ),
    }


def _stage_summary(result: dict[str, Any], family_run: str, reused: bool) -> dict[str, Any]:
    """The stage's report row of a :func:`fewshot_generation` ``result``: what was adapted and
    fine-tuned, and each conditioner's and arm's scores."""
    summary: dict[str, Any] = {
        "target": result["adapt"].get("target"),
        "family": result["adapt"].get("family"),
        "family_generator": family_run if is_pretrained(family_run) else "this run",
        "adapted_tokenizer": "the adapt stage's" if reused else "adapted here",
        "shots": result["fine_tune"]["shots"],
        "family_samples": result["fine_tune"]["family_samples"],
        "generator_steps": result["fine_tune"]["steps"],
    }
    for row in result["scores"]:
        arm = row["arm"].split(" ")[0].replace("-", "_").replace("(", "")
        for score in SCORE_KEYS:
            if score in row:
                summary[f"{row['conditioner'].split(':', 1)[1]}_{arm}_{score}"] = row[score]
    return summary

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
import json
import shutil
import sys
from pathlib import Path
from typing import Any, Sequence

import torch

from vqtouch.core import Assembly, ConfigError, atomic_write, PluginHost, StageJob, StageUnavailable
from vqtouch.plugins.data.sensor_folders import folder_of
from vqtouch.plugins.runtime.run_dir import RunDir, interrupted_status
from vqtouch.core.checkpoint import is_pretrained
from vqtouch.plugins.utils.splits import experiment_split
from vqtouch.plugins.utils.files import FileModel, read_model
from vqtouch.plugins.utils.images import image_grid, save_png
from vqtouch.plugins.runtime.outputs import staged_output
from vqtouch.plugins.evaluation.records import markdown_table, provenance

from .fewshot_generation_plugin import FEWSHOT_FOLDER, FEWSHOT_OPTIONS, FewshotSection  # noqa: F401 (their old home)


class FewshotRecord(FileModel):
    """What is read back of a ``fewshot.json``: the settings it ran with and its score rows."""

    images: str
    shots: int
    ratio: float
    seed: int
    scores: list[dict[str, Any]]


#: The scores of a row, and their headers.
SCORE_KEYS = ("fd_effnetlite0", "contact_psnr", "classifier_accuracy")
SCORE_HEADERS = {
    "fd_effnetlite0": "fd_effnetlite0 ↓",
    "contact_psnr": "contact PSNR ↑ (paired)",
    "classifier_accuracy": "classifier acc. ↑ (paired)",
}
#: The new sensor's images of the family's training scenes the classifier learns (at most).
CLASSIFIER_IMAGES = 512
#: What the classifier accuracy is, for the tables.
CLASSIFIER_TEXT = (
    "classifier accuracy: how often a classifier trained on the adapted tokenizer's reconstructions of the new "
    "sensor's images of the family's training scenes names each sample's condition class (its ceiling: the same "
    "on the reconstructions of the sensor's images of the held-out conditions; chance: one over the classes):"
)
#: The row of the classifier's ceiling: the adapted tokenizer's reconstructions of the paired truth.
RECONSTRUCTED = "new sensor, reconstructed (ceiling)"
#: The arms every conditioner's samples are scored beside.
ARMS = ("few-shot", "zero-shot", "shots (copied)", "no-contact background")


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


def _cycled(images_N3HW: torch.Tensor, count: int) -> torch.Tensor:
    return images_N3HW.repeat(-(-count // len(images_N3HW)), 1, 1, 1)[:count]


def _samples(pipe: Any, index: int, conditions: Any, seed: int, device: torch.device, batch_size: int) -> torch.Tensor:
    """Pipeline ``pipe``'s images of ``conditions`` from conditioner ``index`` at its default settings."""
    from vqtouch.plugins.generator import sample_images

    conditioner = pipe.conditioners[index]
    images = []
    for start in range(0, len(conditions.indices), batch_size):
        batch = conditions.batch(start, start + batch_size, device=device)
        with torch.no_grad():
            tokens = conditioner(conditioner.condition_of(batch))
            images.append(
                sample_images(
                    pipe.generator,
                    conditioner,
                    pipe.tokenizer,
                    pipe.sampler,
                    tokens,
                    conditions.indices[start : start + batch_size],
                    steps=pipe.settings["steps"],
                    guidance=pipe.guidance_for(index),
                    truncation=pipe.settings["truncation"],
                    seed=seed,
                    device=device,
                    precision=pipe.sample_precision,
                )
                .float()
                .clamp(0, 1)
                .cpu()
            )
    return torch.cat(images)


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
    from vqtouch.plugins.adaptation import AdaptSettings, adapt_tokenizer, families_to_adapt_from, registered_source
    from vqtouch.plugins.generator import check_condition_keys, fine_tune_for_sensor, load_pipeline

    ratio = AdaptSettings.ratio if ratio is None else ratio
    if ratio < 0:
        raise ConfigError(f"--ratio {ratio}: family images per shot must be >= 0 (0: the shots alone)")
    out = Path(out)
    tokenizer, folder = _family_tokenizer(family_run, host)
    reused = None
    if adapted is not None:
        adapted = Path(adapted)
        reused = adapted_summary(adapted, folder, rebase=rebase)
        if reused is None:
            raise ConfigError(
                f"{adapted} was not adapted from {folder}, the tokenizer of {family_run}'s generator,"
                f"{'' if rebase else ', not'} re-based; adapt that one (leave the adapted tokenizer out)"
            )
    family_pipe = load_pipeline(family_run, host=host)
    config = family_pipe.config
    # The family data the fine-tuning reads, before anything is written.
    check_condition_keys(config, host, family_pipe.conditioners)
    image_size = config.data.image_size
    result: dict[str, Any] = {
        "family_run": str(family_run),
        "images": images,
        "shots": shots,
        "ratio": ratio,
        "seed": seed,
    }
    reads = [("--images", "images", images)] if folder_of(images) is not None else []
    if not is_pretrained(family_run):  # what it reads of the run: the fewshot stage writes beside them
        reads += [("--run", "family run", Path(family_run) / name) for name in ("checkpoints", "config.json")]
    if families is not None:
        reads.append(("--families", "sensor families", families))
    with staged_output(out, overwrite=overwrite, reads=reads) as partial:
        if adapted is not None:
            report(f"1/5 reuse the tokenizer adapted in {adapted}")
            shutil.copytree(adapted, partial / "tokenizer")
            summary = reused
        else:
            report(f"1/5 assign and adapt the tokenizer of {folder} ({tokenizer_steps} steps)")
            if families is None:
                report("    no --families: clustering the registered sensor families and 3 variants of each")
            fitted = families_to_adapt_from(
                tokenizer,
                folder,
                host,
                families=Path(families) if families else None,
                where=f"the families in {families}",
                exclude=registered_source(images),
                seed=seed,
            )
            settings = AdaptSettings(
                shots=shots,
                ratio=ratio,
                steps=tokenizer_steps,
                eval_images=eval_images,
                threshold=threshold,
                family=family,
                seed=seed,
                part=tokenizer_part,
                rebase=rebase,
            )
            summary = adapt_tokenizer(
                str(folder),
                images,
                fitted,
                host,
                partial / "tokenizer",
                settings,
                report=lambda line: report(f"    {line}"),
                family_background_3HW=family_background(config, host) if rebase else None,
            )
        result["adapt"] = {
            key: summary[key]
            for key in ("target", "family", "assignment", "steps", "held_out", "before", "after")
            if key in summary
        }
        name, shots_N3HW, held_out_M3HW, background_3HW, background_source = new_sensor_images(
            images, host, shots=shots, eval_images=eval_images, image_size=image_size, seed=seed
        )

        report(f"2/5 fine-tune the family generator on {shots} shots and {ratio:g} family samples per shot")
        family_sensor = config.sensor.name if getattr(config, "sensor", None) is not None else "family"
        result["fine_tune"] = fine_tune_for_sensor(
            family_run,
            partial / "tokenizer",
            shots_N3HW,
            background_3HW,
            partial / "generator",
            host,
            ratio=ratio,
            steps=generator_steps,
            seed=seed,
            sensor_names=(family_sensor, name),
            argv=argv,
            report=lambda line: report(f"    {line}"),
        )
        result["fine_tune"]["tokenizer"] = str((out / "tokenizer").resolve())  # where it is once moved into place

        pipe = load_pipeline(partial / "generator", host=host)
        result |= sample_and_score(
            pipe,
            family_pipe,
            images,
            name,
            partial,
            host,
            held_out_M3HW=held_out_M3HW,
            shots_N3HW=shots_N3HW,
            background_3HW=background_3HW,
            samples=samples,
            seed=seed,
            feature_size=feature_size,
            score=score,
            report=report,
        )
        result["background"] = background_source
        report("5/5 write fewshot.json and fewshot.md")
        record = {**result, "provenance": provenance()}
        (partial / "fewshot.json").write_text(json.dumps(record, indent=2, default=str) + "\n")
        (partial / "fewshot.md").write_text("\n".join(render_markdown(result)) + "\n")
    return result


def paired_truth(config: Any, images: str, indices: Sequence[int], host: PluginHost) -> torch.Tensor | None:
    """The new sensor's images of the held-out conditions' own contacts, when they exist: the family's
    data rendered by that sensor (``images`` a registered sensor or variant whose family renders; None
    for a folder of captured images, which pairs with nothing)."""
    from vqtouch.core import VqtouchError, validate_experiment

    if folder_of(images) is not None:
        return None
    spec = json.loads(images) if images.strip().startswith("{") else {"name": images}
    data = config.to_dict() | {"sensor": spec}
    try:
        rendered = Assembly(validate_experiment(data, host), host).component("data.dataset")
    except VqtouchError:
        return None
    if rendered.rendering_sensor() is None:
        return None
    return torch.stack([rendered[index]["tactile"] for index in indices]).float()


def sample_and_score(
    pipe: Any,
    family_pipe: Any,
    images: str,
    name: str,
    out: Path,
    host: PluginHost,
    *,
    held_out_M3HW: torch.Tensor,
    shots_N3HW: torch.Tensor,
    background_3HW: torch.Tensor,
    samples: int,
    seed: int,
    feature_size: int,
    score: bool = True,
    report: Any = print,
) -> dict[str, Any]:
    """Steps 3 and 4: sample every condition with the fine-tuned ``pipe`` and the zero-shot ``family_pipe``
    (pictures into ``out``) and score them; the ``conditioners``, ``samples`` and ``scores`` entries of
    ``fewshot.json``.  Draws depend on ``seed`` and each condition's index only, so scoring a finished
    run again draws the same images."""
    from vqtouch.plugins.generator import held_out_conditions

    config, device = family_pipe.config, family_pipe.device
    dataset = Assembly(config, host).component("data.dataset")
    train, held_out = experiment_split(dataset, config.data, config.seed)
    conditions = held_out_conditions(held_out, dataset, min(samples, len(held_out_M3HW)), device)
    count = len(conditions.indices)
    if count == 0:
        raise ConfigError("the family's data hold no held-out conditions to generate from")
    real_M3HW = held_out_M3HW[:count]
    names = pipe.conditioner_names()
    report(f"3/5 sample {count} images of the new sensor from each condition ({', '.join(names)})")
    generated: dict[str, dict[str, torch.Tensor]] = {}
    shown = min(count, 8)
    overview: list[torch.Tensor] = []  # samples.png: each condition's row(s), then the real images
    for index, label in enumerate(names):
        fewshot_images = _samples(pipe, index, conditions, seed, device, 16)
        zero_shot_images = _samples(family_pipe, index, conditions, seed, device, 16)
        generated[label] = {"few-shot": fewshot_images, "zero-shot": zero_shot_images}
        rows = []
        batch = conditions.batch(0, shown, device=torch.device("cpu"))
        condition = batch.get(pipe.conditioners[index].sample_key)
        if isinstance(condition, torch.Tensor) and condition.ndim == 4 and condition.shape[1] == 3:
            rows.append(condition.float())
        overview += [*rows, fewshot_images[:shown]]
        rows += [fewshot_images[:shown], zero_shot_images[:shown], real_M3HW[:shown].float()]
        save_png(image_grid(torch.cat(rows), columns=shown), out / f"samples_{label.replace(':', '_')}.png")
    save_png(image_grid(torch.cat([*overview, real_M3HW[:shown].float()]), columns=shown), out / "samples.png")
    result: dict[str, Any] = {
        "conditioners": names,
        "samples": {
            "count": count,
            "pictures": [f"samples_{label.replace(':', '_')}.png" for label in names],
            "overview": "samples.png",
            "rows": "condition (image conditions only) | few-shot | zero-shot | real new-sensor image",
        },
    }
    if not score:
        report("4/5 scoring skipped (--no-score)")
        return result | {"scores": []}
    paired = paired_truth(config, images, conditions.indices, host)
    classifier = None
    if paired is not None and conditions.labels is not None:
        classifier = classifier_images(config, images, train, pipe.tokenizer, host)
    report(
        f"4/5 score against {count} held-out images of {name} (fd_effnetlite0 at {feature_size} px"
        + ("; contact PSNR against its rendering of each condition's own contact" if paired is not None else "")
        + (
            f"; a classifier trained on the adapted tokenizer's reconstructions of {len(classifier[1])} of its "
            "images of the family's training scenes)"
            if classifier is not None
            else ")"
        )
    )
    result["paired_truth"] = paired is not None
    result["classifier"] = (
        {"train_images": len(classifier[1]), "trained_on": "the adapted tokenizer's reconstructions"}
        if classifier is not None
        else {"skipped": "no paired truth with labels (a folder of captured images, or a dataset without labels)"}
    )
    # One feature network (its weights loaded once) for the fd and the classifier.
    metric = host.build("metric", {"name": "fd_effnetlite0", "image_size": feature_size})
    scores = _scores(generated, real_M3HW, shots_N3HW, background_3HW, metric, paired)
    if classifier is not None:
        accuracy = _classifier_scores(generated, paired, conditions.labels, classifier, pipe.tokenizer, metric, seed)
        for row in scores:
            if (row["conditioner"], row["arm"]) in accuracy:
                row["classifier_accuracy"] = accuracy.pop((row["conditioner"], row["arm"]))
        scores += [
            {"conditioner": label, "arm": arm, "classifier_accuracy": value} for (label, arm), value in accuracy.items()
        ]
    return result | {"scores": scores}


@torch.no_grad()
def classifier_images(
    config: Any, images: str, train: Any, tokenizer: Any, host: PluginHost
) -> tuple[torch.Tensor, list[int]] | None:
    """What the samples' classifier learns: the new sensor's images of the family's first
    :data:`CLASSIFIER_IMAGES` training scenes (``images`` a registered sensor that renders them),
    decoded through the adapted ``tokenizer`` (a classifier fitted on sharp images fails on every
    decoded one, the tokenizer's own reconstructions included), with the scenes' labels; None when
    the sensor renders nothing or the scenes carry no labels."""
    from vqtouch.plugins.evaluation.distribution import labels_of
    from vqtouch.plugins.tokenizer import reconstruct_all

    indices = list(train.indices[:CLASSIFIER_IMAGES])
    labels = labels_of([train.dataset[index] for index in indices])
    rendered = paired_truth(config, images, indices, host) if labels is not None else None
    if rendered is None or len(set(labels)) < 2:
        return None
    return reconstruct_all(tokenizer, rendered.to(tokenizer.device)).float().cpu(), labels


@torch.no_grad()
def _classifier_scores(
    generated: dict[str, dict[str, torch.Tensor]],
    paired_M3HW: torch.Tensor,
    labels: Sequence[int],
    classifier: tuple[torch.Tensor, list[int]],
    tokenizer: Any,
    metric: Any,
    seed: int,
) -> dict[tuple[str, str], float]:
    """``classifier_accuracy`` per (conditioner, arm): how often the classifier of
    :func:`classifier_images` names the class of the arm's samples (sample i's class is held-out
    condition i's), and per conditioner under :data:`RECONSTRUCTED` its ceiling, the same on the
    adapted tokenizer's reconstructions of the new sensor's images of those very conditions."""
    from vqtouch.plugins.evaluation.distribution import DistributionScorer
    from vqtouch.plugins.tokenizer import reconstruct_all

    scorer = DistributionScorer(paired_M3HW, list(labels), classifier[0], classifier[1], metric=metric, seed=seed)
    ceiling = scorer.score(reconstruct_all(tokenizer, paired_M3HW.to(tokenizer.device)).float().cpu())
    accuracy = {}
    for label, arms in generated.items():
        for arm, images in arms.items():
            accuracy[(label, arm)] = scorer.score(images)["classifier_accuracy"]
        accuracy[(label, RECONSTRUCTED)] = ceiling["classifier_accuracy"]
    return accuracy


def _scores(
    generated: dict[str, dict[str, torch.Tensor]],
    real_M3HW: torch.Tensor,
    shots_N3HW: torch.Tensor,
    background_3HW: torch.Tensor,
    metric: Any,
    paired_M3HW: torch.Tensor | None = None,
) -> list[dict[str, Any]]:
    """One row per conditioner and arm: ``fd_effnetlite0`` against the held-out real images and, given
    the new sensor's images of the same contacts (``paired_M3HW``), the contact-region PSNR against them
    (the background's beside it; copied shots have no pairing)."""
    from vqtouch.plugins.evaluation.contact import contact_region_scores
    from vqtouch.plugins.evaluation.distribution import DistributionScorer

    count = len(real_M3HW)
    scorer = DistributionScorer(real_M3HW.float(), metric=metric)
    common = {
        "shots (copied)": scorer.score(_cycled(shots_N3HW.float(), count))["fd_effnetlite0"],
        "no-contact background": scorer.score(background_3HW.float().expand(count, -1, -1, -1))["fd_effnetlite0"],
    }
    rows = []
    for label, arms in generated.items():
        contact: dict[str, float] = {}
        if paired_M3HW is not None:
            background = background_3HW.float().expand(count, -1, -1, -1)
            found = contact_region_scores({**arms, "no-contact background": background}, paired_M3HW, background)
            contact = {arm: round(found[f"{arm}contact_psnr"], 4) for arm in (*arms, "no-contact background")}
        for arm, images in arms.items():
            row = {"conditioner": label, "arm": arm, "fd_effnetlite0": scorer.score(images)["fd_effnetlite0"]}
            rows.append(row | ({"contact_psnr": contact[arm]} if contact else {}))
        for arm, value in common.items():
            row = {"conditioner": label, "arm": arm, "fd_effnetlite0": value}
            rows.append(row | ({"contact_psnr": contact[arm]} if arm in contact else {}))
    return rows


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
        **_fewshot_options(args),
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


def arm_name(arm: str, ratio: float) -> str:
    """An arm's name in the seeds table: the fine-tuned arm by its ratio (``few-shot 1:5``; ``shots
    alone`` at ratio 0), the comparisons as they are."""
    if arm == RECONSTRUCTED:  # the ceiling depends on the adapted tokenizer, so on the ratio
        return f"new sensor, reconstructed by the {'shots-alone' if ratio == 0 else f'1:{ratio:g}'} tokenizer (ceiling)"
    if arm != "few-shot":
        return arm
    return "shots alone" if ratio == 0 else f"few-shot 1:{ratio:g}"


def evaluate_fewshot_generation(
    family_run: str,
    images: str,
    out: Path,
    host: PluginHost,
    *,
    seeds: Sequence[int],
    ratios: Sequence[float],
    report: Any = print,
    overwrite: bool = False,
    **options: Any,
) -> dict[str, Any]:
    """:func:`fewshot_generation` once per seed and ratio into ``out/seed<S>/ratio<R>/`` (a folder that
    already holds a finished run with the same images, shots, ratio and seed is read, not run again: an
    interrupted table resumes; one with other settings is refused unless ``overwrite``, which runs every
    arm again), then ``fd_effnetlite0`` per conditioner and arm as mean ± std over the
    seeds: ``fewshot_generation.json`` and ``fewshot_generation.md``.  The zero-shot, copied-shots and
    background rows of a seed are the same at every ratio (same held-out images and conditions); the
    first ratio's are kept."""
    from vqtouch.plugins.evaluation.records import ExperimentRecord, mean_spread

    record = ExperimentRecord("fewshot_generation", out, seeds, overwrite=overwrite)
    rows: list[dict[str, Any]] = []
    for seed in record.seeds:
        for position, ratio in enumerate(ratios):
            folder = Path(out) / f"seed{seed}" / f"ratio{ratio:g}"
            settings = {"images": images, "shots": options.get("shots", 50), "ratio": ratio, "seed": seed}
            previous = None if overwrite else finished_arm(folder, settings)
            if previous is not None:
                report(f"seed {seed}, ratio {ratio:g}: read {folder / 'fewshot.json'}")
                result = previous
                if ("paired_truth" not in result or "classifier" not in result) and result["scores"]:
                    report("    scored before the paired scores existed: drawing its samples again to score them")
                    result = score_again(folder, family_run, host, report=report, **options)
            else:
                report(f"seed {seed}, ratio {ratio:g} -> {folder}")
                result = fewshot_generation(
                    family_run, images, folder, host, ratio=ratio, seed=seed, overwrite=True, report=report, **options
                )
            for row in result["scores"]:
                if row["arm"] in ("few-shot", RECONSTRUCTED) or position == 0:
                    rows.append({**row, "arm": arm_name(row["arm"], ratio), "seed": seed})
    table = mean_spread(rows, list(SCORE_KEYS), ["conditioner", "arm"])
    result = {"family_run": family_run, "images": images, "ratios": list(ratios), "rows": rows, "summary": table}
    lines = [
        f"# Few-shot generation: {images}",
        "",
        f"Mean ± std over seeds {', '.join(map(str, record.seeds))}.  fd_effnetlite0 (lower is better): each "
        "conditioner's samples against as many held-out images of the new sensor (never the shots).  Where the "
        "sensor renders the family's scenes (paired): contact PSNR against its image of each condition's own "
        f"contact, and {CLASSIFIER_TEXT}",
        "",
        *markdown_table(table, ["conditioner", "arm"], list(SCORE_KEYS), SCORE_HEADERS),
    ]
    record.write(result, lines)
    return result


def finished_arm(folder: Path, settings: dict[str, Any]) -> dict[str, Any] | None:
    """The ``fewshot.json`` of an arm finished with ``settings`` (None when there is none); a finished arm
    with other settings is refused in one line: it is replaced only with ``--overwrite``."""
    done = folder / "fewshot.json"
    if not done.is_file():
        return None
    previous = read_model(done, FewshotRecord).model_dump()
    differing = {key: previous.get(key) for key, value in settings.items() if previous.get(key) != value}
    if differing:
        said = ", ".join(f"{key} {previous.get(key)!r} (now {settings[key]!r})" for key in differing)
        raise ConfigError(
            f"{folder} holds a finished arm with other settings: {said}; pass --overwrite to run every arm "
            "again, or choose another --out"
        )
    return previous


def score_again(
    folder: Path,
    family_run: str,
    host: PluginHost,
    *,
    eval_images: int = 64,
    samples: int = 32,
    feature_size: int = 224,
    report: Any = print,
    **_: Any,
) -> dict[str, Any]:
    """Steps 3 to 5 again on a finished ``vqtouch fewshot`` output (its generator run is kept): the same
    draws, scored with what this version scores; rewrites its ``fewshot.json`` and ``fewshot.md``."""
    from vqtouch.plugins.generator import load_pipeline

    result = read_model(folder / "fewshot.json", FewshotRecord).model_dump()
    images, shots, seed = result["images"], result["shots"], result["seed"]
    family_pipe = load_pipeline(family_run, host=host)
    name, shots_N3HW, held_out_M3HW, background_3HW, _ = new_sensor_images(
        images, host, shots=shots, eval_images=eval_images, image_size=family_pipe.config.data.image_size, seed=seed
    )
    result |= sample_and_score(
        load_pipeline(folder / "generator", host=host),
        family_pipe,
        images,
        name,
        folder,
        host,
        held_out_M3HW=held_out_M3HW,
        shots_N3HW=shots_N3HW,
        background_3HW=background_3HW,
        samples=samples,
        seed=seed,
        feature_size=feature_size,
        report=report,
    )
    atomic_write(folder / "fewshot.json", lambda tmp: tmp.write_text(json.dumps(result, indent=2, default=str) + "\n"))
    atomic_write(folder / "fewshot.md", lambda tmp: tmp.write_text("\n".join(render_markdown(result)) + "\n"))
    return result


def _evaluate_fewshot_generation_command(args: argparse.Namespace) -> int:
    out = Path(args.out)
    evaluate_fewshot_generation(
        args.run,
        args.images,
        out,
        args.host,
        seeds=args.seeds,
        ratios=args.ratios,
        report=lambda line: print(line, flush=True),
        overwrite=args.overwrite,
        **_fewshot_options(args),
    )
    print((out / "fewshot_generation.md").read_text())
    print(f"-> {out} (fewshot_generation.json, fewshot_generation.md, seed*/ratio*/)")
    return 0


def _fewshot_options(args: argparse.Namespace) -> dict[str, Any]:
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
    summary: dict[str, Any] = {
        "target": result["adapt"].get("target"),
        "family": result["adapt"].get("family"),
        "family_generator": family_run if is_pretrained(family_run) else "this run",
        "adapted_tokenizer": "the adapt stage's" if reuse is not None else "adapted here",
        "shots": result["fine_tune"]["shots"],
        "family_samples": result["fine_tune"]["family_samples"],
        "generator_steps": result["fine_tune"]["steps"],
    }
    for row in result["scores"]:
        arm = row["arm"].split(" ")[0].replace("-", "_").replace("(", "")
        for score in SCORE_KEYS:
            if score in row:
                summary[f"{row['conditioner'].split(':', 1)[1]}_{arm}_{score}"] = row[score]
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

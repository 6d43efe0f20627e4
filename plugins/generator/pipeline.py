"""Generating tactile images from a trained run: :func:`load_pipeline` and :class:`GenerationPipeline`.

::

    from vqtouch.plugins.generator import load_pipeline

    pipe = load_pipeline("runs/l2t")                 # a generator run (or a demo run that trained one)
    images_B3HW = pipe(label=[3, 3], steps=25, seed=0)

Sample ``i`` of a call is drawn with its own random generator seeded from (seed, i), so the same
seed and settings give the same images whatever the batch size.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from collections.abc import Iterator
from typing import Any

import torch

from vqtouch.core import CheckpointError, ConfigError, PluginHost, VqtouchError, load, load_plugins
from vqtouch.plugins.utils.seeding import resolve_device
from vqtouch.plugins.runtime.run_dir import RunDir
from vqtouch.core.checkpoint import is_pretrained, open_pretrained
from vqtouch.core.components import IMAGE_SAMPLE_KEYS
from vqtouch.core.image_size import ImageSize
from vqtouch.plugins.utils.images import read_condition_image
from vqtouch.plugins.training.checkpoints import TRAINER_STATE, apply_ema_weights, saved_ema_weights
from vqtouch.plugins.training.precision import autocast
from vqtouch.plugins.training.batches import collate_samples

from vqtouch.plugins.tokenizer import load_tokenizer, tokenizer_digest, tokenizer_location

from .best_of import BestOfRank, check_best_of, check_best_of_rank, sample_best_of
from .stage import CHECKPOINT_FOLDER, sampling_precision
from .training import SENSOR_TAG_MODULE, SensorTaggedConditioner


@dataclass
class GenerationPipeline:
    """A trained generator with its tokenizer, conditioners and default sampling settings."""

    tokenizer: Any
    generator: Any
    conditioners: list[Any]
    sampler: Any
    sampler_name: str
    settings: dict[str, Any]
    class_names: list[str]
    image_size: ImageSize
    host: PluginHost
    device: torch.device
    checkpoint: Path
    #: The experiment config the generator was trained with (its run's, or the bundle's recorded one).
    config: Any = None
    #: The run it was loaded from; None for a bundle (``pretrained:NAME``), which is read-only.
    run: RunDir | None = None
    #: A sensor-tagged generator's tag (``generator.sensor_tag``, made by ``vqtouch fewshot``); the
    #: conditioners then draw the sensor ``generator.sample_sensor`` names.  None for most generators.
    sensor_tag: Any = None
    #: The code judge of best of K, fitted on first use (:meth:`code_judge`).
    _judge: Any = field(default=None, repr=False)
    #: Best of K's consensus ranking, built on first use (:meth:`contact_consensus`).
    _consensus: Any = field(default=None, repr=False)
    #: The run's training split and its no-contact image, read on first use (:meth:`training_split`).
    _training: Any = field(default=None, repr=False)

    def training_split(self, needs: str) -> tuple[Any, torch.Tensor | None, str]:
        """``(train, background_3HW, how it was made)``: the run's training split (the one ``vqtouch
        evaluate generation`` holds its conditions out of) and its no-contact image
        (:func:`~vqtouch.plugins.evaluation.contact.dataset_background`), read once per loaded run
        for the best-of-K rankings.  A ConfigError naming ``needs`` (what asked) when the pipeline
        was built without a config."""
        if self.config is None:
            raise ConfigError(f"{needs} needs the run's config (its training split)")
        if self._training is None:
            from vqtouch.core import Assembly
            from vqtouch.plugins.utils.splits import experiment_split
            from vqtouch.core.image_size import image_hw
            from vqtouch.plugins.evaluation.contact import dataset_background

            dataset = Assembly(self.config, self.host).component("data.dataset")
            train, _ = experiment_split(dataset, self.config.data, self.config.seed)
            self._training = (train, *dataset_background(train, image_hw(self.config.data.image_size)))
        return self._training

    def code_judge(self) -> Any:
        """The :class:`~.judge.CodeJudge` that ranks best of K's candidates: fitted, on first use, on the
        canonical codes of the training split the generator learned from (the split ``vqtouch evaluate
        generation`` holds its conditions out of), seeded by the run's seed; about a minute on a CPU.
        A ConfigError when the run's training samples carry no labels."""
        if self._judge is None:
            import sys

            from vqtouch.plugins.evaluation.distribution import labels_of

            from .codes import canonical_background
            from .judge import codebook_of, fit_code_judge

            train, background_3HW, _ = self.training_split("best of K by the code judge")
            print(f"fitting the code judge on {len(train)} training images (about a minute on a CPU)", file=sys.stderr)
            samples = [train[i] for i in range(len(train))]
            labels = labels_of(samples)
            if labels is None:
                raise ConfigError(
                    "best of K by the code judge needs labelled training samples; this run's have none "
                    "(use --best-of-rank posterior)"
                )
            with torch.no_grad():
                codes = torch.cat(
                    [
                        self.tokenizer.encode_codes(
                            torch.stack([s["tactile"] for s in samples[start : start + 64]]).to(self.device)
                        )
                        for start in range(0, len(samples), 64)
                    ]
                )
                if background_3HW is not None:
                    codes, _ = canonical_background(codes, self.tokenizer, background_3HW.to(self.device))
            self._judge = fit_code_judge(
                codes,
                torch.tensor(labels, device=codes.device),
                codebook_of(self.tokenizer),
                # Every class a label conditioner can ask for, even one absent from the training split.
                max(
                    [
                        len(self.class_names or []),
                        max(labels) + 1,
                        *(c.num_classes for c in self.conditioners if isinstance(getattr(c, "num_classes", None), int)),
                    ]
                ),
                seed=self.config.seed,
            )
        return self._judge

    def contact_consensus(self) -> Any:
        """The :class:`~.consensus.ContactConsensus` that ranks best of K's candidates by ``consensus``:
        this run's tokenizer and the no-contact image of its training split (the one ``vqtouch
        evaluate generation`` scores contacts against).  A ConfigError when the run has no config or
        its data give no no-contact image."""
        if self._consensus is None:
            from .consensus import ContactConsensus

            _, background_3HW, source = self.training_split("best of K by consensus")
            if background_3HW is None:
                raise ConfigError(f"best of K by consensus needs a no-contact image; this run's data give {source}")
            self._consensus = ContactConsensus(self.tokenizer, background_3HW)
        return self._consensus

    def best_of_ranking(self, rank: BestOfRank) -> Any:
        """What ranks best of K's candidates: the code judge's :meth:`~.judge.CodeJudge.rank` for
        ``"judge"``, None (the generator's own posterior) for ``"posterior"``, the
        :meth:`contact_consensus` for ``"consensus"``."""
        rank = check_best_of_rank(rank)
        if rank == "consensus":
            return self.contact_consensus()
        return self.code_judge().rank if rank == "judge" else None

    def check_steps(self, steps: Any) -> int:
        """``steps`` as given, or a one-line ConfigError: sampling steps are an integer in [1, T] (the
        generator's diffusion steps; any positive integer for a generator that has no limit)."""
        limit = getattr(self.generator, "max_steps", None)
        if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1 or (limit and steps > limit):
            raise ConfigError(
                f"--steps {steps}: steps must be an integer in [1, {limit}] (the generator's diffusion steps)"
                if limit
                else f"--steps {steps}: steps must be a positive integer"
            )
        return steps

    def conditioner_names(self) -> list[str]:
        """``INDEX:NAME`` of each conditioner, in training order (``0:label``, ``1:visual``, ...)."""
        blocks = self.config.generator.conditioners if self.config is not None else []
        names = (
            [block.name for block in blocks]
            if len(blocks) == len(self.conditioners)
            else [type(c).__name__ for c in self.conditioners]
        )
        return [f"{index}:{name}" for index, name in enumerate(names)]

    @property
    def sample_precision(self) -> str:
        """The precision (fp32 or bf16) the generator's network samples in on this pipeline's device:
        the run's ``generator.sample_precision``, ``auto`` resolved (:func:`.stage.sampling_precision`)."""
        return sampling_precision(self.settings.get("precision", "auto"), self.device)

    def guidance_for(self, index: int) -> float:
        """The default guidance scale of conditioner ``index``: the run's ``conditioner_guidance`` for
        its name, else its ``guidance`` (:meth:`GeneratorSection.guidance_for`)."""
        if self.config is None:
            return float(self.settings["guidance"])
        return self.config.generator.guidance_for(self.conditioner_names()[index].split(":", 1)[1])

    def conditioner_for(self, key: str, which: int | str | None = None) -> Any:
        """The conditioner that reads samples' ``key`` (see :meth:`conditioner_index`)."""
        return self.conditioners[self.conditioner_index(key, which)]

    def conditioner_index(self, key: str, which: int | str | None = None) -> int:
        """The index of the conditioner that reads samples' ``key`` (label, visual, tactile, text, ...);
        ``tactile`` also finds one reading ``tactile_source`` (the conditioning tactile image, whichever
        entry holds it).  ``which`` (an index or a conditioner name, as ``vqtouch generate
        --conditioner``) chooses among several; with several and no choice, a ConfigError lists them."""
        wanted = (key, "tactile_source") if key == "tactile" else (key,)
        names = self.conditioner_names()
        if which is not None:
            index = self._conditioner_index(which, names)
            if self.conditioners[index].sample_key not in wanted:
                raise ConfigError(
                    f"--conditioner {which}: conditioner {names[index]} reads samples' "
                    f"{self.conditioners[index].sample_key!r}, not {key!r}; give a "
                    f"--{self.conditioners[index].sample_key.removesuffix('_source')} condition or "
                    "choose another conditioner"
                )
            return index
        for accepted in wanted:
            matching = [i for i, conditioner in enumerate(self.conditioners) if conditioner.sample_key == accepted]
            if len(matching) > 1:
                raise ConfigError(
                    f"this generator has {len(matching)} conditioners reading {accepted!r} "
                    f"({', '.join(names[i] for i in matching)}); choose one with --conditioner "
                    "INDEX|NAME"
                )
            if matching:
                return matching[0]
        have = ", ".join(sorted({c.sample_key for c in self.conditioners}))
        raise ConfigError(f"this generator was not trained with a {key!r} condition; it takes: {have}")

    @staticmethod
    def _conditioner_index(which: int | str, names: list[str]) -> int:
        text = str(which)
        if text.isdecimal() and int(text) < len(names):
            return int(text)
        by_name = [i for i, label in enumerate(names) if label.split(":", 1)[1] == text or label == text]
        if len(by_name) == 1:
            return by_name[0]
        reason = "names several" if by_name else "is none of"
        raise ConfigError(
            f"--conditioner {which} {reason} this generator's conditioners ({', '.join(names)}); give its index"
        )

    def __call__(self, n: int | None = None, **options: Any) -> torch.Tensor:
        """Images (n, 3, S, S) in [0, 1] for one condition, given as ``key=value`` (``label=3``) or
        ``key=[v1, v2, ...]`` (one per image); a single value is repeated ``n`` times.  ``options`` are
        those of :meth:`batches` (sampling settings, seed, batch size, conditioner, the condition),
        which gives the same images a batch at a time, for more than fit in memory."""
        return torch.cat([images for _, images in self.batches(n, **options)])

    @torch.no_grad()
    def batches(
        self,
        n: int | None = None,
        *,
        steps: int | None = None,
        sampler: str | None = None,
        guidance: float | None = None,
        truncation: float | None = None,
        seed: int = 0,
        batch_size: int = 16,
        conditioner: int | str | None = None,
        best_of: int = 1,
        best_of_rank: BestOfRank = "judge",
        **conditions: Any,
    ) -> Iterator[tuple[int, torch.Tensor]]:
        """``(index of the first image, images (B, 3, S, S))`` a batch at a time, in order, holding one batch
        at most; :meth:`__call__` concatenates them.  An image depends on its index and the seed only,
        never on the batch it falls in.

        Unset settings take the run's own (``generator.steps``, ``sampler``, the conditioner's
        guidance (:meth:`guidance_for`), ``truncation``).  ``conditioner``: which conditioner (index
        or name) when several read the condition's key.  ``best_of`` > 1: each image is the best of that
        many candidates by ``best_of_rank``: for a label, the code judge (:meth:`code_judge`) or the
        generator's own posterior of its label; for any condition, the candidates' consensus on the
        contact (:meth:`contact_consensus`) (:mod:`.best_of`; image i with ``best_of=1`` is the same as
        without).  Values are what
        :meth:`vqtouch.core.Conditioner.parse_condition` takes (a class index or name, an image path or
        tensor, a text)."""
        if len(conditions) != 1:
            raise ConfigError(
                "give exactly one condition, e.g. label=3, visual='photo.png' or text='...' "
                f"(got {', '.join(conditions) or 'none'})"
            )
        ((key, value),) = conditions.items()
        values = list(value) if isinstance(value, (list, tuple)) else None
        count = len(values) if values is not None else (n or 1)
        if n is not None and count != n:
            raise ConfigError(f"{count} values of {key} for n={n} images; give one value or n values")
        if count < 1:
            raise ConfigError("nothing to generate: n must be at least 1")
        steps = steps if steps is not None else self.settings["steps"]
        precision = self.sample_precision
        index = self.conditioner_index(key, conditioner)
        guidance = guidance if guidance is not None else self.guidance_for(index)
        truncation = truncation if truncation is not None else self.settings["truncation"]
        self.check_steps(steps)
        chosen = self.sampler if sampler in (None, self.sampler_name) else self.host.build("sampler", sampler)
        conditioner = self.conditioners[index]
        check_best_of_rank(best_of_rank)
        check_best_of(best_of, conditioner, self.conditioner_names()[index], best_of_rank)
        rank = self.best_of_ranking(best_of_rank) if best_of > 1 else None

        def parse(item: Any) -> Any:
            if conditioner.sample_key in IMAGE_SAMPLE_KEYS and not isinstance(item, torch.Tensor):
                item = read_condition_image(item, conditioner.sample_key, self.image_size)
            return conditioner.parse_condition(item, image_size=self.image_size, class_names=self.class_names)

        # A repeated value is parsed once (n may be far larger than what fits in memory); a list is parsed
        # whole first, so that a bad value is refused before anything is generated.
        parsed = [parse(item) for item in values] if values is not None else None
        single = parse(value) if values is None else None
        for start in range(0, count, batch_size):
            rows = (
                parsed[start : start + batch_size] if parsed is not None else [single] * min(batch_size, count - start)
            )
            batch = collate_samples([{conditioner.sample_key: row} for row in rows])
            batch = {k: v.to(self.device) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}
            condition = conditioner(conditioner.condition_of(batch))
            null = conditioner.null(len(rows))

            def draw(generators: list[torch.Generator], condition: Any = condition, null: Any = null) -> torch.Tensor:
                with autocast(precision, self.device):
                    return self.generator.sample(
                        condition,
                        chosen,
                        steps=steps,
                        null=null,
                        guidance=guidance,
                        truncation=truncation,
                        generators=generators,
                    )

            row_seeds = [seed * 1_000_003 + start + row for row in range(len(rows))]
            labels_B = conditioner.condition_of(batch) if best_of > 1 else None
            codes = sample_best_of(
                self.generator, conditioner, labels_B, row_seeds, best_of, draw, self.device, rank=rank
            )
            # Decoded one by one: the decoder's float rounding depends on the batch size (1e-6), which
            # could flip a pixel's 8-bit value, and a sample must not depend on its batch.
            yield start, torch.cat([self.tokenizer.decode_codes(grid.unsqueeze(0)).cpu() for grid in codes])


def load_pipeline(
    run: str | Path,
    *,
    host: PluginHost | None = None,
    step: int | str | None = None,
    device: str | None = None,
    weights: str | None = None,
) -> GenerationPipeline:
    """The generation pipeline of a run whose ``generator`` stage trained (its newest good checkpoint,
    ``step``, or ``"best"``), with the tokenizer it was trained on; or of a bundle, ``pretrained:NAME``
    (its tokenizer, generator and conditioners, with the config of the run that trained them).

    ``weights``: ``"ema"`` samples with the moving average of the weights that training kept
    (``generator.train.ema_decay``; a ConfigError when the checkpoint holds none), ``"raw"`` with the
    raw weights; None follows ``generator.sample_weights`` (EMA when the checkpoint holds one).  A
    bundle holds one set, recorded when it was exported."""
    host = host or load_plugins()
    if weights not in (None, "ema", "raw"):
        raise ConfigError(f"--weights {weights!r}: choose ema or raw")
    if is_pretrained(run):
        if step is not None:
            raise ConfigError(f"--step belongs to runs; {run} is a bundle with one checkpoint")
        pipe = _bundle_pipeline(str(run), host, device)
        if weights is not None and weights != pipe.settings["weights"]:
            raise ConfigError(
                f"--weights {weights}: {run} holds its {pipe.settings['weights']} weights only (chosen at export)"
            )
        return pipe
    run_dir = RunDir.open(run)
    config = run_dir.load_config(host)
    section = getattr(config, "generator", None)
    if section is None or section.model is None:
        raise ConfigError(
            f"{run_dir.path}: its config has no generator (generator.model); train one with `vqtouch train generator`"
        )
    device_ = resolve_device(device or config.device)
    folder = run_dir.checkpoint(host, step, required_files=("generator.safetensors",), stage=CHECKPOINT_FOLDER)
    generator = load(folder / "generator.safetensors", host=host, map_location=device_).eval()
    conditioners = [
        load(folder / f"conditioner_{index}.safetensors", host=host, map_location=device_).eval()
        for index in range(len(section.conditioners))
    ]
    sensor_tag = None
    if section.sensor_tag is not None:
        sensor_tag = load(folder / f"{SENSOR_TAG_MODULE}.safetensors", host=host, map_location=device_).eval()
    used = _use_ema_weights(
        folder, generator, conditioners, weights or section.sample_weights, strict=bool(weights), sensor_tag=sensor_tag
    )
    if sensor_tag is not None:
        conditioners = [SensorTaggedConditioner(c, sensor_tag, section.sample_sensor) for c in conditioners]
    tokenizer, _ = load_tokenizer(generator_tokenizer(run_dir, section), host, device=str(device_))
    if section.sampler is None:
        raise ConfigError(f"{run_dir.path}: generator.sampler is empty; pass sampler=NAME")
    sampler = host.build("sampler", section.sampler)
    class_names = _class_names(config, host)
    settings = _sampling_settings(section) | {"weights": used}
    return GenerationPipeline(
        tokenizer,
        generator,
        conditioners,
        sampler,
        section.sampler.name,
        settings,
        class_names,
        config.data.image_size,
        host,
        device_,
        folder,
        config,
        run_dir,
        sensor_tag,
    )


def _use_ema_weights(
    folder: Path, generator: Any, conditioners: list[Any], wanted: str, *, strict: bool, sensor_tag: Any = None
) -> str:
    """Which weights the loaded modules hold after honouring ``wanted`` (``ema``/``raw``): the moving
    average the trainer kept in step ``folder`` replaces the raw weights of every module, or of none.
    ``strict`` (the user asked for ``ema``): a checkpoint without one is an error, not raw weights."""
    if wanted == "raw":
        return "raw"
    modules = {"generator": generator} | {f"conditioner_{i}": module for i, module in enumerate(conditioners)}
    if sensor_tag is not None:
        modules[SENSOR_TAG_MODULE] = sensor_tag
    averages = saved_ema_weights(folder)
    if not averages:
        if strict:
            raise ConfigError(
                f"--weights ema: {folder} holds no EMA weights (trained without generator.train.ema_decay); "
                "use the raw weights or train with an EMA"
            )
        return "raw"
    for name, module in modules.items():
        apply_ema_weights(module, averages.get(name, {}), folder / TRAINER_STATE)
    return "ema"


def _sampling_settings(section: Any) -> dict[str, Any]:
    """A generator section's sampling defaults, as :attr:`GenerationPipeline.settings` holds them."""
    return {
        "steps": section.steps,
        "guidance": section.guidance,
        "truncation": section.truncation,
        "precision": section.sample_precision,
    }


def generator_tokenizer(run_dir: RunDir, section: Any) -> RunDir | Path:
    """Where the tokenizer a run's generator was trained on lives: the checkpoint folder its
    ``generator`` product records, so that a tokenizer trained further afterwards is not picked up
    in its place; for runs without products (made before vqtouch 0.2.0), the section's
    ``tokenizer_run`` or the run itself (its newest tokenizer checkpoint)."""
    generator = run_dir.products().get("generator")
    if generator is None or "tokenizer" not in generator.facts:
        return tokenizer_location(section.tokenizer_run) if section.tokenizer_run else run_dir
    recorded = Path(generator.facts["tokenizer"])
    folder = recorded if recorded.is_absolute() else run_dir.path / recorded
    if not folder.is_dir():
        raise CheckpointError(
            f"{run_dir.path}: its generator was trained on the tokenizer in {folder}, which is "
            "gone; restore that folder or train the generator again"
        )
    pinned = generator.facts.get("tokenizer_sha256")
    if pinned is not None and tokenizer_digest(folder) != pinned:
        raise CheckpointError(
            f"{run_dir.path}: its generator was trained on the tokenizer in {folder}, which has changed since "
            "(retrained or replaced); train the generator again on it, or restore that tokenizer"
        )
    return folder


def _bundle_pipeline(spec: str, host: PluginHost, device: str | None) -> GenerationPipeline:
    """The pipeline of the bundle ``spec`` (``pretrained:NAME``) names: its weights, and the generator
    settings, classes and image size
    of the config recorded in its headers."""
    from vqtouch.core import validate_experiment

    device_ = resolve_device(device or "auto")
    # The package that ships bundles builds on this one, so it is asked through its hook, not imported.
    bundle = open_pretrained(spec, host, device_)
    if not bundle.run_config:
        raise ConfigError(f"{spec}: its headers record no run config; export it again with `vqtouch pretrained export`")
    config = validate_experiment(bundle.run_config, host)
    section = config.generator
    sampler = host.build("sampler", section.sampler)
    settings = _sampling_settings(section) | {"weights": bundle.weights}
    return GenerationPipeline(
        bundle.tokenizer,
        bundle.generator,
        bundle.conditioners,
        sampler,
        section.sampler.name,
        settings,
        _class_names(config, host),
        config.data.image_size,
        host,
        device_,
        bundle.folder / "generator",
        config,
        None,
    )


def _class_names(config: Any, host: PluginHost) -> list[str]:
    """The class names of the run's dataset (labels can then be given by name), without rendering it."""
    from vqtouch.core import Assembly

    try:
        dataset = Assembly(config, host).component("data.dataset")
    except VqtouchError:  # a dataset that cannot be built here (e.g. its folder is elsewhere) only loses the names
        return []
    return list(getattr(dataset, "class_names", []))

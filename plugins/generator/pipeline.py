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

from .best_of import RANKER_KIND, check_best_of, check_best_of_rank, sample_best_of
from .rankers_plugin import DEFAULT_RANKER
from .scoring import sampling_precision
from .stage import CHECKPOINT_FOLDER
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
    #: Best of K's rankers, by name, built on first use (:meth:`best_of_ranker`).
    _rankers: dict[str, Any] = field(default_factory=dict, repr=False)
    #: The names of those prepared for this pipeline (:meth:`best_of_ranking`).
    _prepared_rankers: set[str] = field(default_factory=set, repr=False)
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

    def best_of_ranker(self, name: str) -> Any:
        """The best-of ranker registered as ``name`` (a :class:`~vqtouch.core.BestOfRanker`), built once
        per pipeline and not yet prepared: what :func:`.best_of.check_best_of` reads.  A one-line
        ConfigError naming the registered rankers for any other name."""
        name = check_best_of_rank(name, self.host)
        if name not in self._rankers:
            self._rankers[name] = self.host.build(RANKER_KIND, name)
        return self._rankers[name]

    def best_of_ranking(self, name: str) -> Any:
        """What ranks best of K's candidates by the ranker ``name``: :meth:`best_of_ranker`, prepared for
        this pipeline once (the ``judge`` fits its code judge on the run's training codes, about a minute
        on a CPU; the ``consensus`` reads the run's no-contact image)."""
        ranker = self.best_of_ranker(name)
        if name not in self._prepared_rankers:
            ranker.prepare(self)
            self._prepared_rankers.add(name)
        return ranker

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
        the run's ``generator.sample_precision``, ``auto`` resolved (:func:`.scoring.sampling_precision`)."""
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
        best_of_rank: str = DEFAULT_RANKER,
        **conditions: Any,
    ) -> Iterator[tuple[int, torch.Tensor]]:
        """``(index of the first image, images (B, 3, S, S))`` a batch at a time, in order, holding one batch
        at most; :meth:`__call__` concatenates them.  An image depends on its index and the seed only,
        never on the batch it falls in.

        Unset settings take the run's own (``generator.steps``, ``sampler``, the conditioner's
        guidance (:meth:`guidance_for`), ``truncation``).  ``conditioner``: which conditioner (index
        or name) when several read the condition's key.  ``best_of`` > 1: each image is the best of that
        many candidates by the registered ranker ``best_of_rank`` (:meth:`best_of_ranking`): for a label,
        the code judge or the generator's own posterior of its label; for any condition, the candidates'
        consensus on the contact (:mod:`.best_of`; image i with ``best_of=1`` is the same as without).
        Values are what :meth:`vqtouch.core.Conditioner.parse_condition` takes (a class index or name, an
        image path or tensor, a text)."""
        key, value, values, count = _one_condition(n, conditions)
        plan = self._sampling_plan(
            key,
            conditioner,
            steps=steps,
            sampler=sampler,
            guidance=guidance,
            truncation=truncation,
            best_of=best_of,
            best_of_rank=best_of_rank,
        )
        for start, rows in self._condition_rows(plan.conditioner, value, values, count, batch_size):
            yield start, self._sample_rows(plan, rows, [seed * 1_000_003 + start + row for row in range(len(rows))])

    def _sampling_plan(
        self, key: str, which: int | str | None, *, best_of: int, best_of_rank: str, **settings: Any
    ) -> _SamplingPlan:
        """The checked settings of one :meth:`batches` call: the conditioner reading ``key`` (``which``
        chooses among several), the sampling ``settings`` (None: the run's) and the prepared ranker."""
        precision = self.sample_precision
        index = self.conditioner_index(key, which)
        steps = settings["steps"] if settings["steps"] is not None else self.settings["steps"]
        guidance = settings["guidance"] if settings["guidance"] is not None else self.guidance_for(index)
        truncation = settings["truncation"] if settings["truncation"] is not None else self.settings["truncation"]
        self.check_steps(steps)
        name = settings["sampler"]
        chosen = self.sampler if name in (None, self.sampler_name) else self.host.build("sampler", name)
        conditioner = self.conditioners[index]
        check_best_of(best_of, conditioner, self.conditioner_names()[index], self.best_of_ranker(best_of_rank))
        rank = self.best_of_ranking(best_of_rank) if best_of > 1 else None
        return _SamplingPlan(conditioner, chosen, steps, guidance, truncation, precision, best_of, rank)

    def _condition_rows(
        self, conditioner: Any, value: Any, values: list[Any] | None, count: int, batch_size: int
    ) -> Iterator[tuple[int, list[Any]]]:
        """``(index of the first row, parsed conditions)`` a batch at a time.  A repeated value is parsed
        once (``count`` may be far larger than what fits in memory); a list is parsed whole first, so
        that a bad value is refused before anything is generated."""

        def parse(item: Any) -> Any:
            if conditioner.sample_key in IMAGE_SAMPLE_KEYS and not isinstance(item, torch.Tensor):
                item = read_condition_image(item, conditioner.sample_key, self.image_size)
            return conditioner.parse_condition(item, image_size=self.image_size, class_names=self.class_names)

        parsed = [parse(item) for item in values] if values is not None else None
        single = parse(value) if values is None else None
        for start in range(0, count, batch_size):
            if parsed is not None:
                yield start, parsed[start : start + batch_size]
            else:
                yield start, [single] * min(batch_size, count - start)

    def _sample_rows(self, plan: _SamplingPlan, rows: list[Any], row_seeds: list[int]) -> torch.Tensor:
        """Images (B, 3, S, S) of one batch of parsed conditions, row b drawn from ``row_seeds[b]``."""
        conditioner = plan.conditioner
        batch = collate_samples([{conditioner.sample_key: row} for row in rows])
        batch = {k: v.to(self.device) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}
        condition = conditioner(conditioner.condition_of(batch))
        null = conditioner.null(len(rows))

        def draw(generators: list[torch.Generator]) -> torch.Tensor:
            with autocast(plan.precision, self.device):
                return self.generator.sample(
                    condition,
                    plan.sampler,
                    steps=plan.steps,
                    null=null,
                    guidance=plan.guidance,
                    truncation=plan.truncation,
                    generators=generators,
                )

        labels_B = conditioner.condition_of(batch) if plan.best_of > 1 else None
        codes = sample_best_of(
            self.generator, conditioner, labels_B, row_seeds, plan.best_of, draw, self.device, rank=plan.rank
        )
        # Decoded one by one: the decoder's float rounding depends on the batch size (1e-6), which
        # could flip a pixel's 8-bit value, and a sample must not depend on its batch.
        return torch.cat([self.tokenizer.decode_codes(grid.unsqueeze(0)).cpu() for grid in codes])


@dataclass(frozen=True)
class _SamplingPlan:
    """The checked settings one :meth:`GenerationPipeline.batches` call samples with."""

    conditioner: Any
    sampler: Any
    steps: int
    guidance: float
    truncation: float
    precision: str
    best_of: int
    rank: Any


def _one_condition(n: int | None, conditions: dict[str, Any]) -> tuple[str, Any, list[Any] | None, int]:
    """``(key, value, values, count)`` of :meth:`GenerationPipeline.batches`' one condition: ``values``
    the list given (None for one value, repeated), ``count`` the images to make; a ConfigError otherwise."""
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
    return key, value, values, count


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

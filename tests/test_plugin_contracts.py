"""Contracts every registered plugin must meet, parametrized over the live registries.

The checks themselves are :mod:`vqtouch.plugins.testing`, the helpers third-party authors call
from their own suites; this file holds only the built-ins' tiny options (and the data their
readers need) and checks that the helpers catch broken plugins.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import pytest
import torch
from pydantic import BaseModel, ConfigDict, Field
from torch import nn

from vqtouch.core import (
    Conditioner,
    Metric,
    MissingWeightsError,
    PluginConfig,
    SensorFamily,
    TactileDataset,
    hookimpl,
    load_plugins,
)
from vqtouch.core.plugin_manager import KINDS_BY_NAME
from vqtouch.plugins.testing import DEFAULT_CONTEXT, check_plugin, check_registration

HOST = load_plugins(autoload=False)
ENTRIES = [(entry.kind, entry.name) for entry in HOST.entries()]


# -- the built-ins' tiny options ------------------------------------------------------------------

#: Options that make each built-in small enough to build and run in a fraction of a second.
TINY_OPTIONS: dict[tuple[str, str], dict[str, Any]] = {
    ("autoencoder", "vqgan"): {
        "channels": 8,
        "channel_multipliers": [1, 2],
        "z_channels": 8,
        "embed_dim": 8,
        "norm_groups": 4,
    },
    ("autoencoder", "dm_vqgan"): {
        "channels": 8,
        "channel_multipliers": [1, 2],
        "z_channels": 8,
        "embed_dim": 8,
        "norm_groups": 4,
        "deformable_levels": 1,
    },
    ("autoencoder", "mae"): {
        "patch_size": 8,
        "width": 16,
        "depth": 1,
        "heads": 2,
        "decoder_width": 16,
        "decoder_depth": 1,
    },
    ("quantizer", "vq"): {"codebook_size": 16},
    ("quantizer", "ema_vq"): {"codebook_size": 16},
    ("quantizer", "fsq"): {"levels": [4, 4]},
    ("discriminator", "patchgan"): {"channels": 8, "layers": 2},
    ("conditioner", "tactile"): {"width": 8, "depth": 2, "token_grid": 2},
    ("conditioner", "label"): {"num_tokens": 2},
    ("conditioner", "visual"): {"token_grid": 2, "input_size": 32},
    ("conditioner", "visual_cnn"): {"width": 8, "depth": 2, "token_grid": 2},
    ("conditioner", "text_scratch"): {"depth": 1, "width": 16, "heads": 2, "vocab_buckets": 64, "max_words": 6},
    ("dataset", "procedural"): {"num_samples": 4},
    # A worn, noisy variant: its options must survive checkpoints and its noise follow the generator.
    **{
        ("sensor_family", name): {"variant": {"response_scale": 0.8, "noise_std": 0.02, "damage_spots": 2, "seed": 3}}
        for name in ("gelsight", "gelsight_mini", "digit")
    },
    ("metric", "fd_effnetlite0"): {"image_size": 32, "batch_size": 4},
    ("metric", "kid_effnetlite0"): {"image_size": 32, "batch_size": 4, "subsets": 10},
    ("metric", "kid"): {"subsets": 10},
    ("generator", "vq_diffusion"): {"depth": 1, "width": 16, "heads": 2, "num_steps": 10},
}

# A tiny open_clip model: the clip conditioner is checked with a weights file written from it.
from metric_weights import TINY_RANDOM_CLIP as TINY_CLIP  # noqa: E402  (registered by conftest)


import dataset_fixtures  # noqa: E402  (registered by conftest)
import generator_runs  # noqa: E402  (registered by conftest)
import metric_weights  # noqa: E402  (registered by conftest)

READER_CASES = {case.name: case for case in dataset_fixtures.READER_CASES}


def tiny_clip_weights(folder: Path) -> Path:
    """Write the tiny open_clip model's weights under ``folder`` (skips the test without open_clip)."""
    open_clip = pytest.importorskip("open_clip")
    from safetensors.torch import save_file

    path = folder / "tiny_clip.safetensors"
    if not path.is_file():
        model = open_clip.create_model("ViT-S-32", pretrained=None, **TINY_CLIP)
        save_file({k: v.contiguous() for k, v in model.state_dict().items()}, str(path))
    return path


def builtin_case(
    kind: str, name: str, tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch | None = None
) -> dict[str, Any]:
    """The keyword arguments of ``check_plugin`` for one built-in: its tiny options, the files it
    reads (a dataset layout in miniature, a tiny CLIP, weights files of the real layouts: metrics
    need ``monkeypatch`` to accept those files' digests) and the inputs it declares."""
    options = dict(TINY_OPTIONS.get((kind, name), {}))
    if kind == "metric":
        options.update(
            metric_weights.weighted_metric_options((kind, name), tmp_path_factory.getbasetemp(), monkeypatch)
        )
    case: dict[str, Any] = {"options": options}
    if (kind, name) == ("conditioner", "clip"):
        weights = tiny_clip_weights(tmp_path_factory.getbasetemp())
        options.update(
            {"architecture": "ViT-S-32", "checkpoint": str(weights), "model_overrides": TINY_CLIP, "num_tokens": 2}
        )
    if (kind, name) == ("conditioner", "text"):
        weights = tiny_clip_weights(tmp_path_factory.getbasetemp())
        options.update(
            {"architecture": "ViT-S-32", "checkpoint": str(weights), "model_overrides": TINY_CLIP, "context_length": 4}
        )
    if (kind, name) == ("metric", "clip_score"):
        weights = tiny_clip_weights(tmp_path_factory.getbasetemp())
        options.update({"architecture": "ViT-S-32", "checkpoint": str(weights), "model_overrides": TINY_CLIP})
    if (kind, name) == ("conditioner", "tactile_codes"):
        options["tokenizer"] = str(generator_runs.tiny_tokenizer_folder(tmp_path_factory.getbasetemp()))
    if kind == "dataset" and name in READER_CASES:
        reader = READER_CASES[name]
        options.update(
            {k: v for k, v in reader.config(reader.build(tmp_path_factory.mktemp(name))).items() if k != "name"}
        )
    entry = HOST.registry(kind).get(name)
    if "sensor" in entry.inputs:
        case["inputs"] = {"sensor": HOST.build("sensor_family", "gelsight")}
    return case


# -- every built-in meets its kind's contract ------------------------------------------------------


@pytest.mark.parametrize("kind, name", ENTRIES)
def test_registration_contract(kind, name):
    check_registration(HOST, kind, name)


@pytest.mark.parametrize("kind, name", ENTRIES)
def test_builtin_entry_has_a_versioned_source(kind, name):
    entry = HOST.registry(kind).get(name)
    assert entry.source.distribution == "vqtouch" and entry.source.version


@pytest.mark.parametrize("kind, name", ENTRIES)
def test_builtin_meets_its_contract(kind, name, tmp_path, tmp_path_factory, monkeypatch):
    check_plugin(HOST, kind, name, tmp_dir=tmp_path, **builtin_case(kind, name, tmp_path_factory, monkeypatch))


@pytest.mark.parametrize("kind, name", [entry for entry in ENTRIES if entry[0] == "metric"])
def test_builtin_metrics_are_checked_computing_not_skipped(kind, name, tmp_path_factory, monkeypatch):
    """check_metric passes a skipped metric on its reason alone: every built-in must reach it with
    the files it needs (fabricated, of the real layout), so its behaviour is what is checked."""
    case = builtin_case(kind, name, tmp_path_factory, monkeypatch)
    assert HOST.build(kind, {"name": name, **case["options"]}).skipped is None


#: A 2:3 context (rows, columns): every built-in must work at a sensor's native, non-square aspect.
NATIVE_ASPECT = DEFAULT_CONTEXT.model_copy(update={"image_size": (32, 48), "code_grid": (8, 12)})


#: Inception-v3 resizes every input to 299 x 299, so these add nothing at a native aspect but a minute.
ASPECT_BLIND = {("metric", "fid"), ("metric", "kid")}


@pytest.mark.parametrize("kind, name", [entry for entry in ENTRIES if entry not in ASPECT_BLIND])
def test_builtin_meets_its_contract_at_a_native_aspect(kind, name, tmp_path, tmp_path_factory, monkeypatch):
    """The same contract with (32, 48) images and an (8, 12) code grid: shapes follow the aspect."""
    check_plugin(
        HOST,
        kind,
        name,
        context=NATIVE_ASPECT,
        tmp_dir=tmp_path,
        **builtin_case(kind, name, tmp_path_factory, monkeypatch),
    )


def test_every_registry_kind_is_checked():
    """A kind without a behaviour check would pass check_plugin on registration alone."""
    from vqtouch.plugins.testing import registration as testing

    checked = [base for base, _ in testing._BEHAVIOUR_CHECKS]
    unchecked = [
        kind.name for kind in KINDS_BY_NAME.values() if not any(issubclass(kind.base_type, base) for base in checked)
    ]
    assert unchecked == []


def test_missing_weights_skip_names_the_file(monkeypatch):
    monkeypatch.delenv("VQTOUCH_CLIP_CKPT", raising=False)
    monkeypatch.delenv("VQTOUCH_WEIGHTS_DIR", raising=False)
    with pytest.raises(pytest.skip.Exception, match="open_clip_model.safetensors"):
        check_plugin(HOST, "conditioner", "clip")
    with pytest.raises(MissingWeightsError, match="open_clip_model.safetensors"):
        check_plugin(HOST, "conditioner", "clip", missing_weights="raise")


def _section_models(model: type[BaseModel]):
    yield model
    for info in model.model_fields.values():
        annotation = info.annotation
        if isinstance(annotation, type) and issubclass(annotation, BaseModel):
            yield from _section_models(annotation)


def test_experiment_config_fields_are_documented():
    """Core's sections and every stage's own section (the host's experiment model)."""
    from vqtouch.core import ExperimentConfig

    assert {"tokenizer", "generator", "cluster"} <= set(HOST.experiment_model.model_fields)
    models = [ExperimentConfig, *list(_section_models(HOST.experiment_model))[1:]]
    assert len(models) > 5
    for model in models:
        assert model.__doc__, model
        undocumented = [field for field, info in model.model_fields.items() if not info.description]
        assert not undocumented, f"{model.__name__}: {undocumented}"


def test_host_experiment_model_keeps_the_documentation():
    assert HOST.experiment_model.__doc__
    assert HOST.experiment_model.model_json_schema().get("description")


# -- the helpers catch broken plugins ----------------------------------------------------------------
# In-memory third-party plugins, registered as "probe" through their kind's hook.


class ProbeConfig(PluginConfig):
    """Options of the in-memory plugins the contract checks are tried on."""

    name: Literal["probe"] = "probe"
    gain: float = Field(0.3, gt=0, le=1, description="How strongly the input shows in the output.")


def probe_host(make_plugin, kind: str, component_type: type, config: type[PluginConfig] = ProbeConfig):
    """A host with ``component_type(config, context)`` registered as ``probe`` of ``kind``."""

    def register_hook(register):
        register(
            "probe",
            lambda options, context: component_type(options, context),
            config,
            description="An in-memory plugin for the contract checks.",
        )

    register_hook.__name__ = KINDS_BY_NAME[kind].hook
    return load_plugins(autoload=False, extra=[make_plugin(f"probe_{kind}", hookimpl(register_hook))])


class GoodGel(SensorFamily):
    """Grey gel that darkens with the indentation, with a little noise from the generator."""

    def __init__(self, config, context) -> None:
        super().__init__()
        self.gain = config.gain

    def shade(self, height_mm_BHW):
        return 0.7 - self.gain * height_mm_BHW.clamp(0, 1)

    def render(self, height_mm_BHW, generator=None):
        noise = 0.01 * torch.rand(height_mm_BHW.shape, generator=generator)
        return (self.shade(height_mm_BHW) + noise).clamp(0, 1)[:, None].expand(-1, 3, -1, -1).contiguous()


class UnclampedGel(GoodGel):
    def render(self, height_mm_BHW, generator=None):
        return (0.7 - self.gain * height_mm_BHW)[:, None].expand(-1, 3, -1, -1)  # a deep press goes below 0


class NoisyGel(GoodGel):
    def render(self, height_mm_BHW, generator=None):
        return super().render(height_mm_BHW, None)  # noise from the global RNG, not the generator


class FragileGel(GoodGel):
    def render(self, height_mm_BHW, generator=None):
        return super().render(height_mm_BHW, generator) * torch.sqrt(1 - height_mm_BHW / 20)[:, None]  # NaN > 20 mm


class BlindGel(GoodGel):
    def shade(self, height_mm_BHW):
        return torch.full_like(height_mm_BHW, 0.5)


class ForgetfulGel(GoodGel):
    """Draws its gel's shading at build time from the global RNG, which no checkpoint holds."""

    def __init__(self, config, context) -> None:
        super().__init__(config, context)
        self.tone = float(torch.rand(()))  # not in the state dict, not in the config

    def shade(self, height_mm_BHW):
        return 0.2 + 0.5 * self.tone - self.gain * height_mm_BHW.clamp(0, 1) * 0.2


class GoodConditioner(Conditioner):
    """Label embedding, the smallest real conditioner."""

    sample_key = "label"

    def __init__(self, config, context) -> None:
        super().__init__(context.cond_dim, 1)
        self.table = nn.Embedding(context.num_classes, context.cond_dim)

    def encode(self, condition):
        return self.table(condition)[:, None]


class ForgetfulConditioner(GoodConditioner):
    """Its table is a non-persistent buffer: checkpoints lose it, a reload draws another."""

    def __init__(self, config, context) -> None:
        super().__init__(config, context)
        del self.table
        self.register_buffer("lookup", torch.randn(context.num_classes, context.cond_dim), persistent=False)

    def encode(self, condition):
        return self.lookup[condition][:, None]


class StubbornConditioner(GoodConditioner):
    """Ignores the weights it is given on load."""

    def _load_from_state_dict(self, *args, **kwargs):
        pass


class UndroppableConditioner(GoodConditioner):
    def forward(self, condition, drop_mask_B=None):
        return super().forward(condition, None)


class WideConditioner(GoodConditioner):
    def encode(self, condition):
        return torch.cat([super().encode(condition)] * 2, dim=-1)


class MeanAbsError(Metric):
    """Mean absolute error (lower is better)."""

    higher_is_better = False

    def __init__(self, config, context) -> None:
        self.reset()

    def update(self, predicted_B3HW, target_B3HW):
        self.total += float((predicted_B3HW - target_B3HW).abs().mean(dim=(1, 2, 3)).sum())
        self.count += len(predicted_B3HW)

    def compute(self):
        return self.total / self.count

    def reset(self):
        self.total, self.count = 0.0, 0


class UpsideDownMetric(MeanAbsError):
    higher_is_better = True


class ForgetNothingMetric(MeanAbsError):
    def __init__(self, config, context) -> None:
        self.total, self.count = 0.0, 0

    def reset(self):
        pass


class LastBatchMetric(MeanAbsError):
    def update(self, predicted_B3HW, target_B3HW):
        self.reset()
        super().update(predicted_B3HW, target_B3HW)


class GoodDataset(TactileDataset):
    """Three seeded flat-colour samples with labels."""

    class_names = ["soft", "hard"]

    def __init__(self, config, context) -> None:
        self.size = context.image_size

    def __len__(self):
        return 3

    def __getitem__(self, index):
        colour = torch.rand(3, 1, 1, generator=torch.Generator().manual_seed(index))
        return {
            "tactile": colour.expand(3, self.size, self.size).clone(),
            "label": index % 2,
            "text": "",
            "sensor": "probe",
            "id": f"sample-{index}",
        }


class AnonymousDataset(GoodDataset):
    def __getitem__(self, index):
        sample = super().__getitem__(index)
        del sample["id"]
        return sample


class BrightDataset(GoodDataset):
    def __getitem__(self, index):
        sample = super().__getitem__(index)
        return {**sample, "tactile": sample["tactile"] * 255}


GOOD = [
    ("sensor_family", GoodGel),
    ("conditioner", GoodConditioner),
    ("metric", MeanAbsError),
    ("dataset", GoodDataset),
]


@pytest.mark.parametrize("kind, component_type", GOOD, ids=[kind for kind, _ in GOOD])
def test_check_plugin_passes_a_good_third_party_plugin(make_plugin, tmp_path, kind, component_type):
    host = probe_host(make_plugin, kind, component_type)
    assert isinstance(check_plugin(host, kind, "probe", {"gain": 0.5}, tmp_dir=tmp_path), component_type)


BROKEN = [
    ("sensor_family", UnclampedGel, r"render\(deep\) has values outside \[0, 1\]"),
    ("sensor_family", NoisyGel, "render is not deterministic for a fixed generator"),
    ("sensor_family", FragileGel, r"render\(deep\) has NaN or Inf"),
    ("sensor_family", BlindGel, "renders the same image as no contact"),
    ("sensor_family", ForgetfulGel, "reloaded component computes different outputs"),
    ("conditioner", ForgetfulConditioner, "reloaded component computes different outputs"),
    ("conditioner", StubbornConditioner, "tensor '.*' changed in the checkpoint round trip"),
    ("conditioner", UndroppableConditioner, "must flag exactly the dropped rows"),
    ("conditioner", WideConditioner, r"forward\(condition\) raised RuntimeError.*expected \(B, 1, 16\)"),
    ("metric", UpsideDownMetric, "identical images must score the best value"),
    ("metric", ForgetNothingMetric, r"reset\(\) must forget"),
    ("metric", LastBatchMetric, "updates must accumulate"),
    ("dataset", AnonymousDataset, r"sample 0 lacks \['id'\]"),
    ("dataset", BrightDataset, r"sample 0: tactile has values outside \[0, 1\]"),
]


@pytest.mark.parametrize("kind, component_type, message", BROKEN, ids=[cls.__name__ for _, cls, _ in BROKEN])
def test_check_plugin_catches_a_broken_plugin(make_plugin, tmp_path, kind, component_type, message):
    host = probe_host(make_plugin, kind, component_type)
    with pytest.raises(AssertionError, match=message) as info:
        check_plugin(host, kind, "probe", tmp_dir=tmp_path)
    assert str(info.value).startswith(f"{kind} 'probe': ")


class LooseConfig(ProbeConfig):
    """Accepts anything."""

    model_config = ConfigDict(extra="allow")


class UndocumentedConfig(ProbeConfig):
    """Has an option nobody explained."""

    width: int = 4


class RequiredOptionConfig(ProbeConfig):
    """Cannot be selected by name alone."""

    path: str = Field(description="A file the plugin reads.")


class NoDocstringConfig(PluginConfig):
    name: Literal["probe"] = "probe"


@pytest.mark.parametrize(
    "config, message",
    [
        (LooseConfig, "accepts unknown keys"),
        (UndocumentedConfig, r"fields without description: \['width'\]"),
        (RequiredOptionConfig, "options without a default"),
        (NoDocstringConfig, "has no docstring"),
    ],
    ids=["strict", "documented", "defaults", "docstring"],
)
def test_check_registration_catches_a_broken_config(make_plugin, config, message):
    host = probe_host(make_plugin, "sensor_family", GoodGel, config)
    with pytest.raises(AssertionError, match=message):
        check_plugin(host, "sensor_family", "probe")

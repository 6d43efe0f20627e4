"""The generator samples in ``generator.sample_precision``: ``auto`` is bf16 on a CPU with bf16 matrix
units and fp32 without; fp32 and bf16 force; the diffusion maths stay float32 either way."""

from __future__ import annotations

import json

import pytest
import torch

from vqtouch.plugins.training import precision as training
from vqtouch.plugins.generator import load_pipeline


def _network_dtypes(pipe, **options):
    """The dtypes the linear layers of the generator's network returned while ``pipe`` sampled, and the
    images."""
    seen = set()
    layers = [module for module in pipe.generator.network.modules() if isinstance(module, torch.nn.Linear)]
    assert layers
    handles = [layer.register_forward_hook(lambda module, args, out: seen.add(out.dtype)) for layer in layers]
    try:
        images = pipe(label=0, n=2, steps=3, **options)
    finally:
        for handle in handles:
            handle.remove()
    return seen, images


@pytest.mark.parametrize(
    "matrix_units, setting, expected",
    [
        (True, "auto", torch.bfloat16),
        (False, "auto", torch.float32),
        (True, "fp32", torch.float32),
        (False, "bf16", torch.bfloat16),
    ],
)
def test_the_network_samples_in_the_resolved_precision(tiny_label_run, monkeypatch, matrix_units, setting, expected):
    monkeypatch.setattr(training, "cpu_has_bf16_matrix_units", lambda: matrix_units)
    pipe = load_pipeline(tiny_label_run)
    pipe.settings["precision"] = setting
    assert pipe.sample_precision == {torch.bfloat16: "bf16", torch.float32: "fp32"}[expected]
    seen, images = _network_dtypes(pipe)
    assert seen == {expected}
    assert images.dtype == torch.float32 and bool(torch.isfinite(images).all())
    assert float(images.min()) >= 0 and float(images.max()) <= 1


def test_bf16_sampling_keeps_the_diffusion_maths_in_float32(tiny_label_run, monkeypatch):
    """Under bf16 sampling the sampler still receives float32 log-probabilities."""
    from vqtouch.plugins.generator import diffusion

    pipe = load_pipeline(tiny_label_run)
    pipe.settings["precision"] = "bf16"
    seen = []
    original = diffusion.log_predict_x0

    def recording(logits_BKL):
        out = original(logits_BKL)
        seen.append(out.dtype)
        return out

    monkeypatch.setattr("vqtouch.plugins.generator.vq_diffusion.log_predict_x0", recording)
    pipe(label=0, n=2, steps=3)
    assert pipe.sample_precision == "bf16" and seen and set(seen) == {torch.float32}


def test_the_run_records_what_it_sampled_in(tiny_label_run):
    expected = "bf16" if training.cpu_has_bf16_matrix_units() else "fp32"
    scores = json.loads((tiny_label_run / "generation.json").read_text())
    assert scores["sampled_in"] == expected


def test_a_bad_sample_precision_is_refused_in_one_line(capsys):
    from vqtouch.plugins.cli.app import main

    code = main(["config", "show", "label-to-touch", "--set", "generator.sample_precision=fp16"])
    err = capsys.readouterr().err
    assert code != 0 and "sample_precision" in err and "fp16" in err

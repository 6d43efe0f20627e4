"""Training and sampling precision: what ``precision: auto`` means on each device, and bf16 autocast."""

from __future__ import annotations

import contextlib

import torch

#: What ``precision: auto`` runs in: device type -> component -> precision, ``None`` for every other
#: component; other devices: fp32.  The components are the trained ones (``TrainConfig.component``) and
#: ``"sampling"``, the generator's network while it samples (``generator.sample_precision``).  Measured
#: (docs/results.md, "Training in bf16 on the CPU"): on a CPU with bf16 matrix units the generator trains
#: 1.5x (``tour``) to 2.1x (``tour_wide``) faster per step in bf16 at the same held-out loss after 1,000
#: steps (3 seeds), the tokenizer 1.3x (DM-VQGAN, 64 px) to 2x (128 px) at PSNR, contact PSNR and held-out
#: L1 within the seeds' spread (3 seeds, 600 steps), and a sampling step runs 1.55x (``tour``) to 2.2x
#: (``tour_wide``) faster at scores within the sampling seeds' spread.
#: CUDA: bf16, the tensor-core precision, where ``torch.cuda.is_bf16_supported()``.
AUTO_PRECISION: dict[str, dict[str | None, str]] = {
    "cpu": {"generator": "bf16", "tokenizer": "bf16", "sampling": "bf16", None: "fp32"},
    "cuda": {None: "bf16"},
}


def cpu_has_bf16_matrix_units() -> bool:
    """Whether this CPU multiplies bf16 matrices in hardware (Intel AMX tiles), where bf16 was measured
    faster; without them (AVX2, AVX-512 alone, Arm) bf16 is emulated or unmeasured, so ``auto`` keeps fp32."""
    probe = getattr(torch.cpu, "_is_amx_tile_supported", None)  # private to torch; absent: assume none
    try:
        return bool(probe()) if probe is not None else False
    except RuntimeError:
        return False


def resolve_precision(precision: str, device: torch.device, component: str | None = None) -> str:
    """The precision (``fp32`` or ``bf16``) a run set to ``precision`` trains ``component`` in on ``device``."""
    if precision != "auto":
        return precision
    by_component = AUTO_PRECISION.get(device.type, {})
    choice = by_component.get(component, by_component.get(None, "fp32"))
    if choice == "bf16" and device.type == "cuda" and not torch.cuda.is_bf16_supported():
        return "fp32"
    if choice == "bf16" and device.type == "cpu" and not cpu_has_bf16_matrix_units():
        return "fp32"
    return choice


def autocast(precision: str, device: torch.device) -> contextlib.AbstractContextManager:
    """bf16 autocast on ``device`` for ``precision`` ``"bf16"``; a no-op for ``"fp32"`` (resolve ``"auto"``
    first with :func:`resolve_precision`)."""
    if precision == "bf16":
        return torch.autocast(device_type=device.type, dtype=torch.bfloat16)
    if precision != "fp32":
        raise ValueError(f"precision {precision!r}: expected fp32 or bf16 (resolve 'auto' with resolve_precision)")
    return contextlib.nullcontext()

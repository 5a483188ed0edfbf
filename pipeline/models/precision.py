"""Which arithmetic the torch encoders use on this machine: bfloat16 where the CPU computes it natively,
float32 elsewhere, unless the deployment fixes it (``OSCAR_PRECISION``).

Shared by the learned view encoder (:mod:`pipeline.models.focus_encoder`) and the MiniLM text encoder's
batch path (:mod:`pipeline.models.minilm_bert`); both embed within a cosine of about 1e-4 of float32, so
the choice is not part of any fingerprint.
"""

from __future__ import annotations

import os
from typing import Any

PRECISIONS = ("auto", "fp32", "bf16")
#: sets what ``precision="auto"`` means: ``fp32`` for float32 on every machine (the same scores
#: everywhere, e.g. for golden tests), ``bf16``; unset: :func:`bf16_pays` decides
PRECISION_ENV = "OSCAR_PRECISION"


class PrecisionError(ValueError):
    """An unknown precision name."""


def bf16_pays(device: Any) -> bool:
    """Whether bfloat16 is the faster choice on ``device``: a CPU with native bfloat16 arithmetic, either
    AMX tiles (Intel Sapphire Rapids on: the ViT-S/14 2.4-3.3x faster than float32) or AVX512-BF16 (e.g.
    AMD Zen 4: 1.6x); elsewhere float32, since bfloat16 without them is emulated and slower
    (docs/performance.md, "bfloat16 on AVX512-BF16")."""
    import torch

    if device.type != "cpu":
        return False
    for name in ("_is_amx_tile_supported", "_is_avx512_bf16_supported"):
        probe = getattr(torch.cpu, name, None)
        try:
            if probe is not None and bool(probe()):
                return True
        except RuntimeError:
            continue
    return False


def requested(precision: str = "auto") -> str:
    """``precision`` checked, ``auto`` replaced by ``OSCAR_PRECISION`` where that is set (no torch import)."""
    if precision == "auto":  # the environment may decide for every process of a deployment
        precision = os.environ.get(PRECISION_ENV, "").strip().lower() or "auto"
    if precision not in PRECISIONS:
        raise PrecisionError(f"unknown precision {precision!r}; choose one of: {', '.join(PRECISIONS)}")
    return precision


def use_bf16(precision: str, device: Any) -> bool:
    """``precision`` (one of :data:`PRECISIONS`) resolved on ``device``: ``auto`` follows
    ``OSCAR_PRECISION`` where it is set, else :func:`bf16_pays`."""
    precision = requested(precision)
    return precision == "bf16" or (precision == "auto" and bf16_pays(device))

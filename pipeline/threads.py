"""``--torch-threads``: how many threads torch's CPU kernels use, set once per process.

Defaults (``docs/cli.md``):

* query and serve: half the cores, at least 1 and at most 4. Query-time models are small (one ROI, a few
  short texts), so extra threads buy little, and on a busy machine OpenMP threads that outnumber the free
  cores spin against each other: a warm offline query measured 0.9-1.3 s with 2 threads on a loaded
  2-core machine and 40-110 ms with 1 (docs/performance.md, "Cold start").
* onboard: torch's own default (every core, or ``OMP_NUM_THREADS``), since onboarding is batch
  throughput work; ``--torch-threads`` overrides it.
"""

from __future__ import annotations

import argparse
import os
import sys

_applied: int | None = None


def cpu_count() -> int:
    """Cores this process may run on (the affinity mask where the OS has one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def default_query_threads() -> int:
    """Half the cores, clamped to 1..4 (query and serve)."""
    return max(1, min(4, cpu_count() // 2))


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def add_torch_threads_arg(p, default_help: str) -> None:
    """``--torch-threads N`` (default ``None``: the command's documented default)."""
    p.add_argument(
        "--torch-threads",
        type=positive_int,
        default=None,
        metavar="N",
        help=f"threads for torch's CPU kernels (default: {default_help})",
    )


def apply_torch_threads(n: int | None, default: int | None = None) -> int:
    """Set torch's CPU threads once per process (later calls keep the first value); returns the count.

    When torch is not imported yet (the offline CPU path never imports it) the count goes to
    ``OMP_NUM_THREADS``, which torch reads when it is imported; before NumPy is imported it also caps
    its BLAS (``OPENBLAS_NUM_THREADS``, ``MKL_NUM_THREADS``), which the NumPy MiniLM path multiplies with.
    """
    global _applied
    if _applied is not None:
        return _applied
    n = int(n or default or default_query_threads())
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(n)
    else:
        os.environ["OMP_NUM_THREADS"] = str(n)
    if "numpy" not in sys.modules:
        os.environ["OPENBLAS_NUM_THREADS"] = os.environ["MKL_NUM_THREADS"] = str(n)
    _applied = n
    return n

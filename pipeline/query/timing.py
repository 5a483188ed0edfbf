"""The per-part latency breakdown of one query, with model loading counted apart."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any


class PartClock:
    """Times the parts of one query; seconds spent loading models (``load_seconds`` grows) are moved from
    the part that triggered them into ``model_load_ms``."""

    def __init__(self, load_seconds: dict[str, float]) -> None:
        self.load_seconds = load_seconds
        self.start = time.perf_counter()
        self.parts: dict[str, float] = {}
        self.loading = 0.0

    def part(self, name: str, fn: Callable, *args, **kwargs) -> Any:
        """``fn(*args, **kwargs)``, its time (less model loading) recorded as ``name`` (ms)."""
        loaded, t = sum(self.load_seconds.values()), time.perf_counter()
        out = fn(*args, **kwargs)
        load = sum(self.load_seconds.values()) - loaded
        self.loading += load
        self.parts[name] = (time.perf_counter() - t - load) * 1000
        return out

    def timings(self, ranking: dict[str, float]) -> dict[str, float]:
        """``model_load_ms``, the timed parts, the ranking's own timings and ``total_ms``."""
        total = (time.perf_counter() - self.start) * 1000
        return {"model_load_ms": self.loading * 1000, **self.parts, **ranking, "total_ms": total}

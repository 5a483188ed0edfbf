"""Progress output that suits a terminal and a cron log alike.

On a terminal (stderr is a TTY): tqdm bars. Otherwise (cron, a pipe, a log file): no carriage returns and
no escape codes, only plain lines: one when a stage starts, at most one every ``interval`` seconds while
it runs, and one when it is done (counts and seconds), e.g.::

    [progress] render: start, 78 meshes
    [progress] render: 31/78 meshes, 60.2s, 0.51 meshes/s, ETA 1m 31s
    [progress] render: done, 78/78 meshes in 151.0s (0.52 meshes/s)
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable, Iterator
from typing import IO, Protocol

INTERVAL_S = 60.0


class Bar(Protocol):
    """What the executors call on a progress bar (tqdm's subset)."""

    def update(self, n: int = 1) -> None: ...

    def close(self) -> None: ...


def is_terminal(stream: IO | None = None) -> bool:
    """Whether ``stream`` (default stderr) is an interactive terminal."""
    stream = sys.stderr if stream is None else stream
    try:
        return stream.isatty()
    except (AttributeError, ValueError):
        return False


def plural(unit: str) -> str:
    """``mesh`` -> ``meshes``, ``query`` -> ``queries``, ``view`` -> ``views``."""
    if unit.endswith(("s", "sh", "ch", "x")):
        return unit + "es"
    if unit.endswith("y") and unit[-2:-1] not in "aeiou":
        return unit[:-1] + "ies"
    return unit + "s"


def duration(seconds: float) -> str:
    """``42s``, ``3m 05s``, ``2h 07m``: a readable span for an ETA."""
    s = int(round(seconds))
    if s < 60:
        return f"{s}s"
    if s < 3600:
        return f"{s // 60}m {s % 60:02d}s"
    return f"{s // 3600}h {s % 3600 // 60:02d}m"


class LineBar:
    """A progress bar that writes plain lines: start, a throttled count with rate and ETA, done with
    counts, seconds and rate."""

    def __init__(
        self,
        name: str,
        total: int | None,
        unit: str,
        stream: IO | None = None,
        interval: float = INTERVAL_S,
        clock=time.monotonic,
    ):
        self.name, self.total, self.unit, self.interval, self.clock = name, total, unit, interval, clock
        self.stream = sys.stderr if stream is None else stream
        self.n, self.closed = 0, False
        self.t0 = self.last_print = clock()
        self.t_last = self.t0
        self._line(f"start, {total} {plural(unit)}" if total is not None else "start")

    def _count(self) -> str:
        done = f"{self.n}/{self.total}" if self.total is not None else str(self.n)
        return f"{done} {plural(self.unit)}"

    def _line(self, text: str) -> None:
        print(f"[progress] {self.name}: {text}", file=self.stream, flush=True)

    def _rate(self, elapsed: float) -> str:
        return f"{self.n / elapsed:.2f} {plural(self.unit)}/s" if elapsed > 0 else f"? {plural(self.unit)}/s"

    def update(self, n: int = 1) -> None:
        self.n += n
        now = self.clock()
        self.t_last = now
        if now - self.last_print >= self.interval:
            self.last_print = now
            elapsed = now - self.t0
            text = f"{self._count()}, {elapsed:.1f}s, {self._rate(elapsed)}"
            if self.total is not None and self.n and elapsed > 0:
                text += f", ETA {duration(max(0, self.total - self.n) * elapsed / self.n)}"
            self._line(text)

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            elapsed = self.t_last - self.t0
            self._line(f"done, {self._count()} in {elapsed:.1f}s ({self._rate(elapsed)})")


class _Off:
    def update(self, n: int = 1) -> None:
        pass

    def close(self) -> None:
        pass


def bar(name: str, total: int | None, *, unit: str = "item", enabled: bool = True, position: int = 0) -> Bar:
    """One stage's progress: a tqdm bar on a terminal, a :class:`LineBar` elsewhere, nothing if disabled."""
    if not enabled:
        return _Off()
    if not is_terminal():
        return LineBar(name, total, unit)
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=f"{name:<11}", unit=unit, leave=True, position=position, file=sys.stderr)


def stage_bars(totals: dict[str, int], *, unit: str = "mesh", enabled: bool = True) -> dict[str, Bar]:
    """One bar per stage (``name -> total``); stages with nothing to do get no output."""
    return {
        name: bar(name, n, unit=unit, enabled=enabled and n > 0, position=i)
        for i, (name, n) in enumerate(totals.items())
    }


def iterate(
    items: Iterable, name: str, *, total: int | None = None, unit: str = "item", enabled: bool = True
) -> Iterator:
    """Yield ``items`` while showing their progress as :func:`bar` does."""
    if total is None and hasattr(items, "__len__"):
        total = len(items)  # type: ignore[arg-type]
    b = bar(name, total, unit=unit, enabled=enabled)
    try:
        for item in items:
            yield item
            b.update(1)
    finally:
        b.close()

"""Progress output that suits a terminal and a cron log alike.

On a terminal (stderr is a TTY): tqdm bars. Otherwise (cron, a pipe, a log file): no carriage returns and
no escape codes, only plain lines: one when a stage starts, at most one every ``interval`` seconds while
it runs, and one when it is done (counts and seconds), e.g.::

    [progress] render: start, 4 meshes
    [progress] render: done, 4/4 meshes in 6.9s
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


class LineBar:
    """A progress bar that writes plain lines: start, a throttled count, done with counts and seconds."""

    def __init__(
        self, name: str, total: int | None, unit: str, stream: IO | None = None, interval: float = INTERVAL_S
    ):
        self.name, self.total, self.unit, self.interval = name, total, unit, interval
        self.stream = sys.stderr if stream is None else stream
        self.n, self.closed = 0, False
        self.t0 = self.last_print = time.monotonic()
        self.t_last = self.t0
        self._line(f"start, {total} {plural(unit)}" if total is not None else "start")

    def _count(self) -> str:
        done = f"{self.n}/{self.total}" if self.total is not None else str(self.n)
        return f"{done} {plural(self.unit)}"

    def _line(self, text: str) -> None:
        print(f"[progress] {self.name}: {text}", file=self.stream, flush=True)

    def update(self, n: int = 1) -> None:
        self.n += n
        now = time.monotonic()
        self.t_last = now
        if now - self.last_print >= self.interval:
            self.last_print = now
            self._line(f"{self._count()}, {now - self.t0:.1f}s")

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self._line(f"done, {self._count()} in {self.t_last - self.t0:.1f}s")


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

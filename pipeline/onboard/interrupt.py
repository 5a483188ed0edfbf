"""Stopping an onboarding run on SIGINT (Ctrl-C) or SIGTERM without losing finished work.

The first signal only sets a :class:`StopFlag`; the engine looks at it between steps: the step that is
running finishes, its rows and every finished rendering are committed, the render workers are killed,
and the run ends with :class:`RunInterrupted` (how many meshes were kept, how many are left). The next
run does only the rest. A second signal stops at once (``KeyboardInterrupt``): committed work is kept,
work in flight is not. Render workers never see the signals (:func:`signals_blocked` while they are
spawned), so a Ctrl-C in a terminal, which reaches the whole process group, prints no tracebacks.
"""

from __future__ import annotations

import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager

SIGNALS = (signal.SIGINT, signal.SIGTERM)


class StopRequested(Exception):
    """Raised by the engine where a stop was requested, once finished work is committed."""


class RunInterrupted(Exception):
    """A run stopped by a signal after committing its finished work."""

    def __init__(self, signum: int, kept: int, complete: int, left: int, summary=None):
        self.signum, self.kept, self.complete, self.left, self.summary = signum, kept, complete, left, summary
        name = signal.Signals(signum).name
        partial = kept - complete
        detail = f" ({complete} complete, {partial} with some stages left)" if partial else ""
        super().__init__(
            f"interrupted by {name}: kept {kept} mesh{'es' if kept != 1 else ''}{detail}; "
            f"{left} left to do: run the same command again to do only the rest"
        )

    @property
    def exit_code(self) -> int:
        """128 + the signal number, as a shell reports a process stopped by that signal."""
        return 128 + self.signum


class StopFlag:
    """Set by the first SIGINT/SIGTERM of a run; read by the engine between steps."""

    def __init__(self) -> None:
        self.signum: int | None = None

    @property
    def requested(self) -> bool:
        return self.signum is not None

    def request(self, signum: int = signal.SIGINT) -> None:
        if self.signum is None:
            self.signum = signum

    def check(self) -> None:
        """Raise :class:`StopRequested` when a stop was requested."""
        if self.signum is not None:
            raise StopRequested(self.signum)


@contextmanager
def stop_on_signals(flag: StopFlag, quiet: bool = False) -> Iterator[StopFlag]:
    """Turn SIGINT and SIGTERM into ``flag`` while the block runs (a second one raises
    ``KeyboardInterrupt``); the previous handlers come back afterwards. Outside the main thread, where
    Python cannot set handlers, signals keep their usual effect."""
    if threading.current_thread() is not threading.main_thread():
        yield flag
        return

    def handler(signum, frame) -> None:
        if flag.requested:
            raise KeyboardInterrupt
        flag.request(signum)
        if not quiet:
            print(
                f"\n{signal.Signals(signum).name}: stopping after the current step and keeping finished work "
                "(again to stop at once)",
                file=sys.stderr,
                flush=True,
            )

    old = {s: signal.signal(s, handler) for s in SIGNALS}
    try:
        yield flag
    finally:
        for s, h in old.items():
            signal.signal(s, h)


@contextmanager
def signals_blocked() -> Iterator[None]:
    """Block SIGINT and SIGTERM in the calling thread: processes started inside inherit the mask, so a
    Ctrl-C sent to the whole process group reaches only the parent, which stops them itself."""
    old = signal.pthread_sigmask(signal.SIG_BLOCK, SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def ignore_signals() -> None:
    """In a worker process: ignore SIGINT and SIGTERM (its parent stops it)."""
    for s in SIGNALS:
        signal.signal(s, signal.SIG_IGN)

"""A pool of render worker processes with a per-mesh timeout.

A mesh that hangs or crashes its worker (a 5M-face file, a driver fault) becomes an error row; the
worker is killed and replaced, and the run goes on.
"""

from __future__ import annotations

import multiprocessing as mp
import time
from collections import deque
from collections.abc import Iterable, Iterator
from multiprocessing.connection import wait

from pipeline.onboard.config import OnboardConfig
from pipeline.onboard.interrupt import ignore_signals, signals_blocked
from pipeline.onboard.stages import Step
from pipeline.onboard.stages.base import error_row
from pipeline.onboard.stages.render import RENDER_OUT

EGL_HINT = "rendering needs EGL/OpenGL: install libegl1 libegl-mesa0 libgl1 (docs/install.md)"


class RenderSetupError(RuntimeError):
    """A render worker could not start (pyrender / PyOpenGL import, no EGL / OpenGL driver)."""


def _cause(exc: BaseException) -> str:
    """The last line of ``exc``'s traceback (``ImportError: libEGL.so.1: cannot open ...``)."""
    import traceback

    return traceback.format_exception_only(type(exc), exc)[-1].strip()


def _worker_main(conn, cfg: OnboardConfig, run_id: str, step: Step) -> None:
    ignore_signals()  # the parent stops its workers; a Ctrl-C to the process group is its to handle
    try:
        stage = step.stage.runner(cfg, run_id, step)
        stage.warm_up()  # GL context + shaders first: timeouts count a mesh's own time only
    except Exception as exc:  # tell the parent why, instead of dying with the reason on our stderr only
        conn.send(("setup_error", _cause(exc)))
        return
    conn.send("ready")
    while True:
        try:
            item = conn.recv()
        except EOFError:
            return
        if item is None:
            return
        conn.send(stage.render_one(item))


class _Worker:
    def __init__(self, ctx, cfg: OnboardConfig, run_id: str, step: Step):
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_worker_main, args=(child, cfg, run_id, step), daemon=True)
        with signals_blocked():  # inherited: the worker never sees SIGINT/SIGTERM, not even while starting
            self.proc.start()
        child.close()
        self.item: dict | None = None
        self.deadline = 0.0
        self.ready = False

    def kill(self) -> None:
        self.proc.kill()
        self.proc.join(5)
        self.conn.close()


class RenderPool:
    """Renders meshes in ``n`` spawned processes; yields ``(item, rows)`` in completion order.

    ``step`` is the run's rendering step (by default resolved from ``cfg``)."""

    def __init__(self, cfg: OnboardConfig, run_id: str, n: int, timeout_s: float, step: Step | None = None):
        self.cfg, self.run_id, self.timeout_s = cfg, run_id, timeout_s
        self.step = step or cfg.resolve().source
        self._ctx = mp.get_context("spawn")
        self._closing = False
        self._workers = [_Worker(self._ctx, cfg, run_id, self.step) for _ in range(max(1, n))]

    def _fail(self, item: dict, reason: str, kind: str) -> list[dict]:
        base = {"mesh_id": item["mesh_id"], "fingerprint": self.step.fingerprint, "run_id": self.run_id}
        return [error_row(RENDER_OUT, base, reason, kind)]

    def map(self, items: Iterable[dict]) -> Iterator[tuple[dict, list[dict]]]:
        todo = deque(items)
        while not self._closing and (todo or any(w.item is not None for w in self._workers)):
            for w in self._workers:
                if w.ready and w.item is None and todo:
                    w.item = todo.popleft()
                    w.deadline = time.monotonic() + self.timeout_s
                    w.conn.send(w.item)
            starting = [w for w in self._workers if not w.ready]
            busy = [w for w in self._workers if w.item is not None]
            timeout = max(0.0, min(w.deadline for w in busy) - time.monotonic()) if busy else None
            ready = wait(
                [w.conn for w in busy + starting] + [w.proc.sentinel for w in busy + starting], timeout
            )
            now = time.monotonic()
            if self._closing:  # halted from another thread: the workers it killed are no results
                return
            for i, w in enumerate(self._workers):
                if not w.ready:
                    if w.conn in ready:
                        try:
                            msg = w.conn.recv()
                        except (EOFError, OSError):
                            w.proc.join(5)
                            raise RenderSetupError(
                                f"render worker died while starting (exit code {w.proc.exitcode}); {EGL_HINT}; "
                                "run with --workers 0 to see why"
                            ) from None
                        if isinstance(msg, tuple) and msg[0] == "setup_error":
                            raise RenderSetupError(f"render worker failed to start: {msg[1]} ({EGL_HINT})")
                        w.ready = msg == "ready"
                    elif w.proc.sentinel in ready:
                        raise RenderSetupError(
                            f"render worker failed to start (exit code {w.proc.exitcode}); {EGL_HINT}; "
                            "run with --workers 0 to see why"
                        )
                    continue
                if w.item is None:
                    continue
                item = w.item
                if w.conn in ready:
                    try:
                        rows = w.conn.recv()
                    except (EOFError, OSError):
                        rows = None
                    if rows is not None:
                        w.item = None
                        yield item, rows
                        continue
                if w.proc.sentinel in ready and not w.proc.is_alive():
                    code = w.proc.exitcode
                    self._replace(i)
                    yield item, self._fail(item, f"render worker crashed (exit code {code})", "WorkerCrash")
                elif now >= w.deadline:
                    self._replace(i)
                    yield item, self._fail(item, f"render timed out after {self.timeout_s:g} s", "Timeout")

    def _replace(self, i: int) -> None:
        self._workers[i].kill()
        if not self._closing:
            self._workers[i] = _Worker(self._ctx, self.cfg, self.run_id, self.step)

    def halt(self) -> None:
        """Stop now (a run interrupted): kill the workers, meshes in flight included; :meth:`map` ends
        without reporting them."""
        self._closing = True
        for w in self._workers:
            if w.proc.is_alive():
                w.proc.kill()

    def close(self) -> None:
        if self._closing:
            for w in self._workers:
                w.proc.join(5)
            return
        self._closing = True
        for w in self._workers:
            try:
                w.conn.send(None)
            except (OSError, BrokenPipeError):
                pass
        for w in self._workers:
            w.proc.join(5)
            if w.proc.is_alive():
                w.proc.kill()

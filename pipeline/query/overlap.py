"""Run one call of a query's embedding beside the others: the learned encoder's ROI embedding (torch) overlaps
the descriptor, caption, text and local-feature work (OpenCV / NumPy), which do not depend on it.

Each of those releases the GIL in its kernels, so where torch leaves a core free (the query CLI's and the
service's default: half the cores, ``pipeline/threads.py``) the embedding step costs about its longest part
instead of their sum (docs/performance.md, "Learned view encoder"). Where torch already runs on every core
the overlap only makes the two contend (measured: no gain), so the call runs in place, as it does with a
single core or ``OSCAR_OVERLAP_EMBED=0``. The pool is shared by every query of the process (the
service runs queries in threads of its own) and has one thread fewer than the process has cores; when
every one of them is busy (concurrent queries) the call runs in place instead of queueing behind the
others', so concurrency never makes a query wait on another's side call.
"""

from __future__ import annotations

import os
import sys
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TypeVar

from pipeline.threads import cpu_count

T = TypeVar("T")
#: set to 0 to run every part of the embedding in the calling thread
OVERLAP_ENV = "OSCAR_OVERLAP_EMBED"

_pool: ThreadPoolExecutor | None = None
_free: threading.BoundedSemaphore | None = None  # pool threads not running a side call
_pool_lock = threading.Lock()


def overlapping() -> bool:
    """Whether side calls run in the shared pool: not switched off, and torch's CPU threads (when torch is
    loaded) leave at least one core of the process free."""
    if os.environ.get(OVERLAP_ENV, "1").strip() == "0":
        return False
    torch = sys.modules.get("torch")
    busy = torch.get_num_threads() if torch is not None else 1
    return cpu_count() > busy


def _forget_pool() -> None:
    """In a forked child: the parent's pool threads do not exist there, so start a pool of its own."""
    global _pool, _free, _pool_lock
    _pool, _free, _pool_lock = None, None, threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)


def _shared_pool() -> tuple[ThreadPoolExecutor, threading.BoundedSemaphore]:
    global _pool, _free
    with _pool_lock:
        if _pool is None or _free is None:
            n = max(1, cpu_count() - 1)
            _pool, _free = (
                ThreadPoolExecutor(max_workers=n, thread_name_prefix="oscar-embed"),
                threading.BoundedSemaphore(n),
            )
        return _pool, _free


def beside(fn: Callable[[], T]) -> Future[T]:
    """``fn()`` started in the shared pool (or run now, when not :func:`overlapping` or every pool thread is
    busy); ``.result()`` gives its value or raises what it raised."""
    started = beside_if_free(fn)
    if started is not None:
        return started
    done: Future[T] = Future()
    try:
        done.set_result(fn())
    except Exception as exc:  # re-raised by .result(), in the caller's order, as the pool would
        done.set_exception(exc)  # (a Ctrl-C is not held back: it stops the query now, as before)
    return done


def beside_if_free(fn: Callable[[], T]) -> Future[T] | None:
    """``fn()`` started in the shared pool when :func:`overlapping` and a pool thread is free, else
    ``None`` (not run): for work worth doing early only where it costs the query nothing."""
    if not overlapping():
        return None
    pool, free = _shared_pool()
    if not free.acquire(blocking=False):
        return None

    def run() -> T:
        try:
            return fn()
        finally:
            free.release()

    return pool.submit(run)

"""The query service's state: the current store snapshot, a bounded worker pool and latency statistics.

* Snapshot: one :class:`~pipeline.query.api.Retriever` on one store state. Requests take a reference to
  the current snapshot and hold it until they finish. A poller thread compares
  :func:`~pipeline.query.library.store_version` every ``reload_interval`` seconds; on a change it opens a
  new Retriever that shares the loaded models, swaps the reference (one assignment: atomic), and closes
  the old snapshot once its last in-flight request has finished. A snapshot is one consistent set of table
  versions (:mod:`pipeline.snapshot`; commits of a run still in progress wait for its ``runs`` commit),
  leased in the store while open so that ``compact`` does not delete its files (:mod:`pipeline.leases`).
* Recovery: a request that meets a data file that is gone anyway (a reader without a lease, an expired
  one) reloads the newest committed snapshot and runs once more on it; when that fails too it answers 503
  with ``Retry-After`` (:class:`~pipeline.query.errors.StoreUnavailable`).
* Work: model and DuckDB work runs in a thread pool of ``workers`` threads; at most ``max_pending``
  requests may wait or run at once (more get 503), and a request that waits longer than ``timeout``
  seconds gets 504 (its work still finishes in the pool, bounded by the same limits).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

log = logging.getLogger("pipeline.serve")


class Busy(RuntimeError):
    """Too many requests are waiting (the service answers 503)."""


class Snapshot:
    """A Retriever plus the count of requests using it; closed when retired and idle."""

    def __init__(self, retriever) -> None:
        retriever.recover = False  # the service reloads and retries itself, without blocking other requests
        if retriever.lease is not None:
            retriever.lease.relabel("service")
        self.retriever = retriever
        self.version = retriever.version
        self.opened_at = time.time()
        self._users = 0
        self._retired = False
        self._lock = threading.Lock()

    def acquire(self) -> bool:
        with self._lock:
            if self._retired:
                return False
            self._users += 1
            return True

    def release(self) -> None:
        with self._lock:
            self._users -= 1
            close = self._retired and self._users == 0
        if close:
            self.retriever.close()

    def retire(self) -> None:
        with self._lock:
            self._retired = True
            close = self._users == 0
        if close:
            self.retriever.close()


@dataclass
class ServiceLimits:
    """Request limits of the service (see ``docs/serve.md``, "Safety")."""

    max_body_bytes: int = 20 * 1024 * 1024
    max_pixels: int = 40_000_000
    timeout: float = 60.0
    workers: int = 2
    max_pending: int = 64
    max_batch: int = 32
    reload_interval: float = 1.0


class QueryService:
    """Owns the snapshots, the worker pool, the reload poller and the statistics."""

    def __init__(self, retriever, limits: ServiceLimits | None = None, *, torch_threads: int | None = None):
        self.limits = limits or ServiceLimits()
        self.torch_threads = torch_threads
        self._snapshot = Snapshot(retriever)
        self._swap_lock = threading.Lock()
        self.pool = ThreadPoolExecutor(max_workers=self.limits.workers, thread_name_prefix="oscar-query")
        self._pending = threading.BoundedSemaphore(self.limits.max_pending)
        self._latencies: deque[float] = deque(maxlen=2000)
        self._stats_lock = threading.Lock()
        self.started_at = time.time()
        self.counts = {
            "queries": 0,
            "errors": 0,
            "rejected_busy": 0,
            "timeouts": 0,
            "reloads": 0,
            "retries": 0,
        }
        self.last_reload_error: str | None = None
        self._unopenable: tuple[dict, str] | None = None  # newest versions that failed to open, why
        self._stop = threading.Event()
        self._poller: threading.Thread | None = None

    # ------------------------------------------------------------------ snapshots
    @property
    def snapshot(self) -> Snapshot:
        return self._snapshot

    def acquire(self) -> Snapshot:
        """The current snapshot, held until :meth:`Snapshot.release` (retries across a concurrent swap)."""
        while True:
            snap = self._snapshot
            if snap.acquire():
                return snap

    def reload_if_changed(self) -> bool:
        """Open the store's newest consistent snapshot if it differs from the one served; returns whether
        the snapshot changed (commits of a run still in progress do not change it)."""
        from pipeline.query.library import store_version
        from pipeline.snapshot import consistent_versions

        with self._swap_lock:
            old = self._snapshot
            token = store_version(old.retriever.store.root)
            if token == old.version:
                return False
            if consistent_versions(old.retriever.store.root) == old.retriever.versions:
                old.version = token  # nothing this service reads has changed
                return False
            self._swap(old)
            return True

    def reload_after_failure(self, failed: Snapshot, reason: str) -> None:
        """Swap to the newest snapshot after ``failed`` met a vanished file (unless a concurrent request
        already did); raises StoreUnavailable when the newest snapshot cannot be opened."""
        from pipeline.query.errors import StoreUnavailable
        from pipeline.query.recover import damaged, newest_snapshot, one_line

        with self._swap_lock:
            if self._snapshot is not failed:
                return
            newest = newest_snapshot(failed.retriever.store.root)
            if newest == failed.retriever.versions:
                raise damaged(failed.retriever.store.root, reason)
            if self._unopenable is not None and self._unopenable[0] == newest:
                raise StoreUnavailable(self._unopenable[1])  # tried already: no reopen per request
            log.warning("store file gone under version %s (%s): reloading", failed.version, reason)
            try:
                self._swap(failed)
            except Exception as exc:  # noqa: BLE001 - keep serving the old snapshot; this request gets 503
                self.last_reload_error = f"{type(exc).__name__}: {exc}"
                message = f"the store changed under this query and its newest snapshot cannot be opened: {one_line(exc)}"
                self._unopenable = (newest, message)
                raise StoreUnavailable(message) from None

    def _swap(self, old: Snapshot) -> None:
        """Open the newest snapshot and publish it in place of ``old`` (caller holds ``_swap_lock``)."""
        t0 = time.perf_counter()
        new = Snapshot(old.retriever.reopened())
        with self._stats_lock:  # counted before it is published: no answer from it precedes the count
            self.counts["reloads"] += 1
        self._snapshot = new  # requests from now on use the new state
        old.retire()  # closes when its in-flight requests are done
        log.info(
            "store version %s -> %s: %d meshes (reopened in %.0f ms)",
            old.version,
            new.version,
            new.retriever.n_meshes,
            (time.perf_counter() - t0) * 1000,
        )

    def start_polling(self) -> None:
        if self.limits.reload_interval <= 0 or self._poller is not None:
            return
        self._poller = threading.Thread(target=self._poll, name="oscar-store-poller", daemon=True)
        self._poller.start()

    def _poll(self) -> None:
        while not self._stop.wait(self.limits.reload_interval):
            try:
                self.reload_if_changed()
                self.last_reload_error = None
            except Exception as exc:  # a half-written or broken commit: keep serving the old state
                self.last_reload_error = f"{type(exc).__name__}: {exc}"
                log.warning("store reload failed, still serving version %s: %s", self._snapshot.version, exc)

    def close(self) -> None:
        self._stop.set()
        if self._poller is not None:
            self._poller.join(timeout=5)
        self.pool.shutdown(wait=True, cancel_futures=True)
        self._snapshot.retire()

    # ------------------------------------------------------------------ work
    async def run(self, fn: Callable, *args):
        """Run ``fn(retriever, *args)`` in the pool on a held snapshot; 503 when full, 504 on timeout."""
        import asyncio

        if not self._pending.acquire(blocking=False):
            with self._stats_lock:
                self.counts["rejected_busy"] += 1
            raise Busy(f"the service is busy ({self.limits.max_pending} requests in flight); retry later")

        def work():
            try:
                return self._attempts(fn, args)
            finally:
                self._pending.release()

        future = asyncio.get_running_loop().run_in_executor(self.pool, work)
        try:
            return await asyncio.wait_for(asyncio.shield(future), timeout=self.limits.timeout)
        except asyncio.TimeoutError:
            with self._stats_lock:
                self.counts["timeouts"] += 1
            raise

    def _attempts(self, fn: Callable, args: tuple):
        """``fn`` on the current snapshot; once more on the newest one when it met a vanished file."""
        from pipeline.query.errors import StoreUnavailable
        from pipeline.query.recover import one_line, vanished_file

        for attempt in (1, 2):
            snap = self.acquire()
            try:
                return fn(snap.retriever, *args)
            except Exception as exc:
                if not vanished_file(exc, snap.retriever.store.root):
                    raise
                if attempt == 2:
                    raise StoreUnavailable(
                        "the store changed under this query and its newest snapshot failed too: "
                        f"{one_line(exc)}"
                    ) from None
                reason = one_line(exc)
            finally:
                snap.release()
            with self._stats_lock:
                self.counts["retries"] += 1
            self.reload_after_failure(snap, reason)
        raise AssertionError("unreachable")  # the second attempt returns or raises

    def record(self, seconds: float, ok: bool, n: int = 1) -> None:
        with self._stats_lock:
            self.counts["queries"] += n
            if not ok:
                self.counts["errors"] += n
            else:
                self._latencies.append(seconds)

    # ------------------------------------------------------------------ stats
    def stats(self) -> dict:
        import numpy as np

        with self._stats_lock:
            lat = np.asarray(self._latencies, dtype=np.float64) * 1000
            counts = dict(self.counts)
        snap = self._snapshot
        r = snap.retriever

        def pct(q: float):
            return round(float(np.percentile(lat, q)), 3) if len(lat) else None

        return {
            "store": str(r.store.root),
            "store_version": snap.version,
            "snapshot_opened_at": snap.opened_at,
            "profile": r.profile.name,
            "meshes": r.n_meshes,
            "captions": r.text_filter.n_rows,
            "stage1": getattr(r.text_filter, "engine", "exact"),  # which stage-1 path answers (--stage1)
            "stage1_notes": list(getattr(r.text_filter, "notes", ())),
            "views": int(r.tables.views.num_rows),
            **counts,
            "latency_ms": {"p50": pct(50), "p99": pct(99), "window": int(len(lat))},
            "uptime_s": round(time.time() - self.started_at, 3),
            "workers": self.limits.workers,
            "torch_threads": self.torch_threads,
            "last_reload_error": self.last_reload_error,
        }

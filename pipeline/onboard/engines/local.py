"""The local engine: runs the onboarding steps in this process (rendering in worker processes), batch by
batch, committing each batch's rows of every table (:meth:`Engine.commit_batch`)."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator

import pyarrow as pa

from pipeline.onboard.config import RunSpec
from pipeline.onboard.engines.base import Engine, RunSummary, Timer, progress_bars
from pipeline.onboard.interrupt import StopFlag
from pipeline.onboard.plan import Plan
from pipeline.onboard.stages import Step
from pipeline.onboard.stages.render import RENDER_OUT
from pipeline.store import Store


def _prefetch(source: Iterator, maxsize: int, stop: StopFlag, halt: Callable[[], None]) -> Iterator:
    """Drain ``source`` in a thread so render workers keep busy while this thread captions and embeds.

    Once ``stop`` is requested, the results already drained are still yielded, then ``halt()`` stops the
    source (it kills the render workers) and the iteration ends."""
    import queue
    import threading

    q: queue.Queue = queue.Queue(maxsize=max(1, maxsize))
    ended = threading.Event()

    def pump() -> None:
        try:
            for item in source:
                while not ended.is_set():
                    try:
                        q.put(("item", item), timeout=0.2)
                        break
                    except queue.Full:
                        continue
                if ended.is_set():
                    return
            if not ended.is_set():
                q.put(("end", None))
        except BaseException as exc:  # re-raised in the consumer
            if not ended.is_set():
                q.put(("error", exc))

    t = threading.Thread(target=pump, name="render-prefetch", daemon=True)
    t.start()
    try:
        while True:
            if stop.requested:
                ended.set()
                while True:  # what is rendered already is kept
                    try:
                        kind, value = q.get_nowait()
                    except queue.Empty:
                        return
                    if kind == "item":
                        yield value
            try:
                kind, value = q.get(timeout=0.2)
            except queue.Empty:
                continue
            if kind == "end":
                return
            if kind == "error":
                raise value
            yield value
    finally:
        ended.set()
        if t.is_alive():
            halt()
        t.join(timeout=5)


class LocalEngine(Engine):
    """Runs a :class:`Plan` in this process; models are built once and reused across batches."""

    def __init__(self, store: Store, run: RunSpec, run_id: str, progress: bool = True, models=None):
        super().__init__(store, run, run_id, progress)
        models = models or {}
        self.runners = {
            s.key: s.stage.runner(run.cfg, run_id, s, model=models.get(s.role)) for s in run.downstream
        }

    def run(self, library: str) -> RunSummary:
        t0 = time.perf_counter()
        plan, summary = self.begin(library)
        self.stop.check()
        self._load_models(plan)
        self.stop.check()
        bars = progress_bars(self.progress, self.run_spec, plan)
        batches = self._rendered_batches(plan, bars[self.run_spec.source.stage.name], summary)
        try:
            # after a stop request, the batches still bring what is rendered; commit_batch keeps it
            for source_out, meshes_rows in batches:
                summary.failed += self.commit_batch(plan, source_out, meshes_rows, bars, self._outputs)
            ids = plan.downstream_ids()
            for i in range(0, len(ids), self.cfg.batch_size):
                self.stop.check()
                chunk = ids[i : i + self.cfg.batch_size]
                with Timer(self.seconds, "load_views"):
                    views = self.stored_rows(self.run_spec.source, chunk)
                summary.failed += self.commit_batch(plan, views, [], bars, self._outputs)
        finally:
            batches.close()  # stops the render workers now, whatever ended the run
            for b in bars.values():
                b.close()
        return self.finish(summary, t0)

    def _load_models(self, plan: Plan) -> None:
        """Build the models this run needs before any rendering, so a missing weight fails fast."""
        with Timer(self.seconds, "model_load"):
            for key, runner in self.runners.items():
                if plan.todo[key]:
                    _ = runner.model

    def _outputs(self, step: Step, mesh_ids: list[str], make_input) -> pa.Table:
        """Run ``step`` here, timed under its stage's name."""
        with Timer(self.seconds, step.stage.name):
            return self.runners[step.key](make_input())

    # ------------------------------------------------------------------ rendering
    def _render_stream(self, items: list[dict]) -> Iterator[tuple[dict, list[dict]]]:
        source = self.run_spec.source
        if self.cfg.workers <= 0:
            stage = source.stage.runner(self.cfg, self.run_id, source)
            for it in items:
                if self.stop.requested:
                    return
                yield it, stage.render_one(it)
            return
        from pipeline.onboard.engines.render_pool import RenderPool

        t0 = time.perf_counter()
        pool = RenderPool(
            self.cfg, self.run_id, min(self.cfg.workers, len(items)), self.cfg.render_timeout_s, source
        )
        try:
            yield from _prefetch(pool.map(items), 2 * self.cfg.batch_size, self.stop, pool.halt)
        finally:
            pool.close()
            # wall time of the render pool, start-up included ("render": the main thread's wait for it)
            self.seconds["render_pool_wall"] = (
                self.seconds.get("render_pool_wall", 0.0) + time.perf_counter() - t0
            )

    def _rendered_batches(self, plan: Plan, bar, summary: RunSummary):
        if not plan.render:
            return
        first_file = plan.file_of()
        items = [
            {"mesh_id": m, "abs_path": first_file[m].abs_path, "format": first_file[m].format}
            for m in plan.render
        ]
        name = self.run_spec.source.stage.name  # its seconds: the wait for rendered meshes
        pending_rows: list[dict] = []
        pending_meshes: list[dict] = []
        n_in_batch = 0
        t = time.perf_counter()
        for item, rows in self._render_stream(items):
            if self.stop.requested and rows[0].get("error_type") in ("WorkerCrash", "Timeout"):
                continue  # a worker stopped by the signal is no verdict on its mesh
            bar.update(1)
            pending_rows.extend(rows)
            pending_meshes.extend(self.rendered_mesh_rows(plan, item["mesh_id"], rows))
            n_in_batch += 1
            summary.rendered += rows[0].get("error") is None
            if n_in_batch >= self.cfg.batch_size:
                self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t
                yield pa.Table.from_pylist(pending_rows, schema=RENDER_OUT), pending_meshes
                pending_rows, pending_meshes, n_in_batch = [], [], 0
                t = time.perf_counter()
        self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t
        if n_in_batch:
            yield pa.Table.from_pylist(pending_rows, schema=RENDER_OUT), pending_meshes

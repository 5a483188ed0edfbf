"""The Ray engine (``--engine ray``): the onboarding stages on Ray Data, committed by the driver.

The driver plans exactly as the local engine does (:meth:`Engine.begin`), streams one row per mesh
through one ``map_batches`` stage per step (render actors on CPUs, then captioner and encoder actor
pools, on GPUs where the cluster has them) and commits every ``cfg.batch_size`` finished meshes through
the code the local engine commits with (:meth:`Engine.commit_batch`). Only the driver writes the store,
so the parts, keys and fingerprints are those of the local engine: either engine can continue the
other's work. The work runs in rounds: meshes whose batch was lost with a node, a worker or an actor
are re-submitted to fresh pools on the surviving nodes; only a mesh that kills a fresh worker twice
becomes an ``errors`` row (WorkerCrash), and a cluster that cannot finish stops the run with one line.
"""

from __future__ import annotations

import logging
import math
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import pyarrow as pa
import pyarrow.compute as pc

from pipeline import schemas
from pipeline.onboard.config import RunSpec
from pipeline.onboard.engines.base import Engine, RunSummary, Timer, progress_bars
from pipeline.onboard.engines.ray_cluster import (
    ClusterWatch,
    LibraryUnreachableError,
    RayEngineError,
    check_reachable,
    gcs_address,
    log_dir,
    quiet_console,
    quiet_driver_core,
    waiting_actors,
)
from pipeline.onboard.engines.ray_options import RayOptions
from pipeline.onboard.engines.ray_workers import (
    input_keys,
    part_column,
    row_schema,
    timing_columns,
    unpack,
)
from pipeline.onboard.plan import Plan
from pipeline.onboard.stages import Step
from pipeline.store import Store, utcnow

log = logging.getLogger(__name__)

#: lost batches (with no node lost meanwhile) after which a mesh is recorded as failed
MESH_STRIKES = 2
#: seconds between checks of the head and the nodes while a round waits for results
WATCH_PERIOD_S = 1.0
#: seconds to wait, after Ray is shut down, for an aborted round's reader thread to end
PUMP_JOIN_S = 10.0
#: how long an aborted round's Ray Data executor loops get to stop before Ray is shut down
EXECUTOR_JOIN_S = 3.0


@dataclass(frozen=True)
class Layout:
    """Resources of each actor pool, from the options and the cluster's CPUs and GPUs."""

    render_workers: int
    render_cpus: float
    model_cpus: float
    caption_gpus: float
    embed_gpus: float

    def describe(self) -> str:
        return (
            f"{self.render_workers} render actor(s) x {self.render_cpus:g} CPU; model actors "
            f"{self.model_cpus:g} CPU each, captioner {self.caption_gpus:g} GPU, encoders {self.embed_gpus:g} GPU"
        )


#: GPU share of an encoder actor when GPUs are shared out (CLIP and DINOv2 are small next to LLaVA)
ENCODER_GPU_SHARE = 0.25


def plan_layout(
    opts: RayOptions, cpus: float, gpus: float, n_caption: int, n_embed: int, n_render: int
) -> Layout:
    """Share the cluster. With GPUs, encoder actors get a quarter GPU at most and the captioners share
    the rest (at most one each); without, model actors get a small CPU share. The render actors split
    the remaining CPUs, one actor per CPU by default."""
    n_model = n_caption + n_embed
    if opts.gpus_per_actor is not None:
        caption_gpus = embed_gpus = opts.gpus_per_actor
    elif gpus >= 0.01 and n_model:
        embed_gpus = min(ENCODER_GPU_SHARE, gpus / n_model)
        caption_gpus = min(1.0, (gpus - embed_gpus * n_embed) / n_caption) if n_caption else 0.0
    else:
        caption_gpus = embed_gpus = 0.0
    model_cpus = opts.model_actor_cpus
    if model_cpus is None:
        model_cpus = 1.0 if max(caption_gpus, embed_gpus) > 0 else 0.25
    left = max(0.5, cpus - n_model * model_cpus)
    workers = opts.render_workers or max(1, min(max(n_render, 1), math.floor(cpus)))
    render_cpus = max(0.05, min(1.0, math.floor(100 * left / workers) / 100))
    return Layout(workers, render_cpus, model_cpus, caption_gpus, embed_gpus)


class RoundStalled(Exception):
    """A round that stopped moving after a node loss (see ``RayOptions.stall_s``); what it committed."""

    def __init__(self, received: set[str], waited: float, actors: int) -> None:
        waiting = f"{actors} actor(s) waiting" if actors else "every actor placed"
        super().__init__(f"no batch for {waited:.0f} s after a node loss, {waiting}")
        self.received = received


class RayEngine(Engine):
    """Runs a :class:`Plan` on Ray Data; models live in the actors, never in the driver."""

    STOP_BETWEEN_STEPS = False  # a batch arrives with every step done: a stop request keeps all of it

    def __init__(self, store: Store, run: RunSpec, run_id: str, progress: bool = True):
        super().__init__(store, run, run_id, progress)
        self.layout: Layout | None = None
        self.library_root: str | None = None
        self._pumps: list = []  # the threads that read each round's results
        self._started = False  # this run connected to Ray (and may disconnect and connect again)

    # ------------------------------------------------------------------ run
    def run(self, library: str) -> RunSummary:
        t0 = time.perf_counter()
        plan, summary = self.begin(library)
        self.library_root = plan.library_root
        items = self._items(plan)
        if items:
            bars = progress_bars(self.progress, self.run_spec, plan)
            try:
                with Timer(self.seconds, "ray_start"):
                    started = self._started = _start_ray(self.cfg.ray)
                with quiet_console():  # until Ray Data's threads of an aborted round have ended too
                    try:
                        self._run_dataset(plan, items, bars, summary)
                    finally:
                        self._stop(started)
            finally:
                for b in bars.values():
                    b.close()
        return self.finish(summary, t0)

    def _stop(self, started: bool) -> None:
        """Disconnect from Ray (if this run connected), then let the threads of an aborted round end:
        this round's reader and Ray Data's executor, which would otherwise reconnect to Ray on their own
        (Ray's auto-connect) and print their errors after the run."""
        import threading

        import ray
        import ray._private.auto_init_hook as auto_init

        live = [t for t in self._pumps if t.is_alive()]
        executors = [t for t in threading.enumerate() if t.name.startswith("StreamingExecutor")] if live else []
        live += executors
        saved, auto_init.enable_auto_connect = auto_init.enable_auto_connect, False
        try:
            end_executor_loops(executors)
            if started:
                try:
                    ray.shutdown()
                except (Exception, SystemExit):  # noqa: BLE001 - a lost head: the run's own error is the one to report
                    log.debug("ray.shutdown failed", exc_info=True)
            for t in live:
                t.join(timeout=PUMP_JOIN_S)
        finally:
            auto_init.enable_auto_connect = saved

    # ------------------------------------------------------------------ inputs
    def _items(self, plan: Plan) -> list[dict]:
        """One row per mesh with work: what to render, which steps it needs, where stored inputs are."""
        first_file = plan.file_of()
        rows = []
        for m in plan.render:
            f = first_file[m]
            rows.append(self._item(plan, m, abs_path=f.abs_path, fmt=f.format))
        rows_stored = [self._item(plan, m) for m in plan.downstream_ids()]
        # inputs that are not produced in this run are read from the store by the render actors
        need: dict[str, list[str]] = {k: [] for k in input_keys(self.run_spec)}
        for r in rows_stored:
            for inp in dict.fromkeys(self.run_spec.step(k).input for k in r["todo"]):
                if inp is not None and inp not in r["todo"]:
                    need[inp].append(r["mesh_id"])
        for inp, ids in need.items():
            step = self.run_spec.step(inp)
            at = self._locate(step.dataset, step.fingerprint, ids)
            for r in rows_stored:
                r[part_column(inp)] = at.get(r["mesh_id"])
        return rows + rows_stored

    def _item(self, plan: Plan, mesh_id: str, abs_path=None, fmt=None) -> dict:
        return {
            "mesh_id": mesh_id,
            "abs_path": abs_path,
            "format": fmt,
            "todo": [s.key for s in self.run_spec.steps if mesh_id in plan.todo[s.key]],
        }

    def _locate(self, dataset: str, fp: str, mesh_ids: list[str]) -> dict[str, str]:
        """mesh_id -> the part file holding its latest rows at ``fp`` (workers read only that file)."""
        d = self.store.dataset(dataset)
        if d is None or not mesh_ids:
            return {}
        flt = pc.field("mesh_id").isin(mesh_ids) & (pc.field("fingerprint") == fp)
        t = d.to_table(columns=["mesh_id", "run_id", "__filename"], filter=flt)
        best: dict[str, tuple[str, str]] = {}
        for m, run, path in zip(*(t.column(c).to_pylist() for c in t.column_names), strict=True):
            if m not in best or run > best[m][0]:
                best[m] = (run, path)
        base = self.store.path_of(dataset)  # a Delta dataset names its files relative to the table
        return {m: str((base / p).resolve()) for m, (_, p) in best.items()}

    # ------------------------------------------------------------------ the dataset
    def _run_dataset(self, plan: Plan, items: list[dict], bars, summary: RunSummary) -> None:
        import ray.data

        ctx = ray.data.DataContext.get_current()
        saved = (ctx.max_errored_blocks, ctx.enable_progress_bars, ctx.print_on_execution_start)
        ctx.max_errored_blocks = -1  # a lost batch is dropped from the round and re-submitted by the driver
        ctx.enable_progress_bars = False
        ctx.print_on_execution_start = False
        ctx.execution_options.preserve_order = False
        try:
            self._stream(plan, items, bars, summary)
        finally:
            ctx.max_errored_blocks, ctx.enable_progress_bars, ctx.print_on_execution_start = saved

    def _stream(self, plan: Plan, items: list[dict], bars, summary: RunSummary) -> None:
        """Run the items in rounds: each round streams its meshes through the actor pools and commits
        what comes back; meshes whose batch was lost go to the next round. A batch lost while a node
        died is an infrastructure failure and is simply redone; a batch lost on its own counts against
        its meshes, which are then retried one per batch, so that a mesh is recorded as failed only
        when it kills a fresh worker a second time."""
        watch = ClusterWatch(gcs_address() if self.cfg.ray.address else None)
        check_reachable(self._reach(plan, items))
        strikes: dict[str, int] = {}
        infra: dict[str, int] = {}
        pending, isolate, received_any = items, False, False
        while pending:
            stalled_round = False
            try:
                received = self._round(plan, pending, bars, summary, watch, isolate)
            except RoundStalled as stalled:  # planned for nodes that are gone: plan again on those alive
                log.info("round abandoned: %s", stalled)
                received, stalled_round = stalled.received, True
                self._reconnect(watch, pending, received)
            received_any |= bool(received)
            if self.stop.requested:  # interrupted: no new round; the re-run does the rest
                break
            lost = [r for r in pending if r["mesh_id"] not in received]
            if not lost:
                break
            # a stalled round is abandoned only after a node loss (which its stall check has already
            # recorded in the watch): its meshes are not to blame either
            dead = watch.check() or stalled_round
            for r in lost:
                counter = infra if dead else strikes
                counter[r["mesh_id"]] = counter.get(r["mesh_id"], 0) + 1
            bad = [r for r in lost if strikes.get(r["mesh_id"], 0) >= MESH_STRIKES]
            if bad and not received_any and not watch.lost:
                raise RayEngineError(
                    f"every batch failed on the Ray cluster ({len(bad)} meshes); see the Ray logs in "
                    f"{log_dir()} (`ray logs`)"
                )
            if bad:
                summary.failed += self._commit_lost(plan, bad)
            pending = [r for r in lost if strikes.get(r["mesh_id"], 0) < MESH_STRIKES]
            summary.redone += len(pending)
            summary.lost_nodes = watch.describe_lost()
            self._check_can_go_on(watch, pending, infra)
            isolate = isolate or any(strikes.get(r["mesh_id"]) for r in pending)
        watch.check()  # a node lost while it held no unfinished work is still named
        summary.lost_nodes = watch.describe_lost()

    def _check_can_go_on(self, watch: ClusterWatch, pending: list[dict], infra: dict[str, int]) -> None:
        """Stop the run (what finished is committed) when the cluster cannot do the rest."""
        if not pending:
            return
        lost = ", ".join(watch.describe_lost()) or "none"
        if watch.cpus_left() <= 0:
            raise RayEngineError(
                f"the Ray cluster cannot finish: no node with CPUs is left (lost: {lost}); "
                f"{len(pending)} meshes are not done, the finished ones are committed; run the same "
                "command again when the cluster is back"
            )
        if max(infra.get(r["mesh_id"], 0) for r in pending) > self.cfg.ray.max_retries:
            raise RayEngineError(
                f"the Ray cluster kept losing nodes ({lost}): {len(pending)} meshes were lost "
                f"{self.cfg.ray.max_retries + 1} times and are not done; the finished ones are "
                "committed; run the same command again"
            )

    def _reach(self, plan: Plan, items: list[dict]) -> dict[str, str]:
        """The folders every node must read: the library (to render) and the store (stored inputs)."""
        source = self.run_spec.source.key
        paths = {}
        if any(source in r["todo"] for r in items):
            paths["library"] = plan.library_root
        if any(r.get(part_column(k)) for r in items for k in input_keys(self.run_spec)):
            paths["store"] = str(self.store.root)
        return paths

    def _round(
        self, plan: Plan, items: list[dict], bars, summary: RunSummary, watch: ClusterWatch, isolate: bool
    ) -> set[str]:
        """One pass of ``items`` through the pools; the mesh ids that came back (and were committed).
        Raises :class:`RayEngineError` when the head is lost or no node is left to run on."""
        import queue
        import threading

        import ray

        resources, settled = self._resources(watch)
        ds = self._dataset(items, resources, isolate)
        out: queue.Queue = queue.Queue()  # at most a couple of batches wait here (the pump holds back)
        stop = threading.Event()

        def pump() -> None:
            try:
                for batch in ds.iter_batches(batch_size=self.cfg.batch_size, batch_format="pyarrow"):
                    while out.qsize() >= 2 and not stop.is_set():
                        time.sleep(0.05)
                    if stop.is_set():
                        return
                    out.put(("batch", batch))
                out.put(("end", None))
            except BaseException as exc:  # noqa: BLE001 - re-raised in the driver's thread
                if not stop.is_set():
                    out.put(("error", exc))

        thread = threading.Thread(target=pump, name="ray-round", daemon=True)
        thread.start()
        self._pumps.append(thread)
        received: set[str] = set()
        # a round planned while Ray still listed a lost node alive may stall on it: watch it as if the
        # loss happened in this round
        lost_before, moved = (len(watch.lost) if settled else 0), time.monotonic()
        try:
            while True:
                try:
                    kind, value = out.get(timeout=WATCH_PERIOD_S)
                except queue.Empty:
                    self._watch(watch, items, received)
                    self._check_stalled(watch, lost_before, moved, received)
                    continue
                moved = time.monotonic()
                if kind == "end":
                    return received
                if kind == "error":
                    self._watch(watch, items, received)  # a lost head or cluster, said in one line
                    if isinstance(value, SystemExit):  # Ray's way out when it loses the cluster
                        raise RayEngineError(
                            f"lost the connection to the Ray cluster (Ray logs: {log_dir()})"
                        ) from None
                    raise value
                rows = value.to_pylist()
                self._commit_rows(plan, rows, bars, summary)
                received |= {r["mesh_id"] for r in rows}
                if self.stop.requested:  # SIGINT/SIGTERM: what arrived is committed, the rest waits
                    return received
        except ray.exceptions.RayError as exc:
            setup = _setup_error(exc)
            if setup is exc:
                raise RayEngineError(
                    f"the Ray run failed: {type(exc).__name__}: {str(exc).splitlines()[0][:300]} "
                    f"(full traceback in the Ray logs, {log_dir()})"
                ) from exc
            raise setup from exc
        finally:
            stop.set()

    def _resources(self, watch: ClusterWatch) -> tuple[dict[str, float], bool]:
        """What a round is planned for, and whether Ray's node table agrees with it: the cluster's
        resources; after a node loss, only the nodes alive now, once Ray's table marks the lost ones dead
        (a round planned and placed while Ray still counts a killed node waits for ever for its actors,
        and no node is lost in it to abandon it by)."""
        import ray

        if not watch.lost:
            return ray.cluster_resources(), True
        settled = watch.settle()
        if not settled:
            log.warning(
                "Ray still lists lost node(s) %s as alive; planning on the nodes that answer",
                ", ".join(watch.describe_lost()),
            )
        return watch.resources(), settled

    def _check_stalled(self, watch: ClusterWatch, lost_before: int, moved: float, received: set[str]) -> None:
        """Raise :class:`RoundStalled` when, since a node of this round was lost, no batch came for
        ``stall_s`` seconds while an actor of the run waits to be placed; or when, after any node loss
        of the run, no batch came for ``stall_placed_s`` seconds whatever Ray says of its actors (a run
        with no node lost is never abandoned: its work is just slow)."""
        opts = self.cfg.ray
        waited = time.monotonic() - moved
        if waited < opts.stall_s:
            return
        watch.check()
        if len(watch.lost) > lost_before:
            actors = waiting_actors()
            if actors:
                raise RoundStalled(set(received), waited, actors)
        limit = opts.stall_placed_s if opts.stall_placed_s is not None else 5 * opts.stall_s
        if watch.lost and waited >= limit:
            raise RoundStalled(set(received), waited, 0)

    def _reconnect(self, watch: ClusterWatch, pending: list[dict], received: set[str]) -> None:
        """Disconnect (Ray ends this driver's actors, the stalled round's with them) and connect again,
        so that the next round is planned on the nodes alive. Only when this run connected to Ray itself;
        a caller's own Ray session is not dropped: the run stops instead, what finished is committed."""
        left = len([r for r in pending if r["mesh_id"] not in received])
        if not self._started:
            raise RayEngineError(
                f"the Ray cluster cannot finish: after losing {', '.join(watch.describe_lost())} its "
                f"actors wait for room the surviving nodes lack; {left} meshes are not done, the finished "
                f"ones are committed; run the same command again (Ray logs: {log_dir()})"
            )
        self._stop(True)
        self._started = _start_ray(self.cfg.ray)

    def _watch(self, watch: ClusterWatch, items: list[dict], received: set[str]) -> None:
        """While a round waits: stop when the head is gone or no node with CPUs is left."""
        left = len(items) - len(received)
        if not watch.head_reachable():
            raise RayEngineError(
                f"lost the Ray head node (GCS at {watch.gcs_address} unreachable): {left} meshes of this "
                "round are not done, the finished ones are committed; run the same command again when the "
                f"cluster is back (Ray logs: {log_dir()})"
            )
        if watch.cpus_left() <= 0:
            watch.check()
            raise RayEngineError(
                f"the Ray cluster cannot finish: no node with CPUs is left (lost: "
                f"{', '.join(watch.describe_lost()) or 'none'}); {left} meshes are not done, the finished "
                "ones are committed; run the same command again when the cluster is back"
            )

    def _dataset(self, items: list[dict], resources: dict, isolate: bool = False):
        """The Ray Data pipeline: render/load actors, then captioner and encoder actor pools (one mesh
        per batch everywhere when ``isolate``: a retry after a batch was lost on its own)."""
        with warnings.catch_warnings():
            # max_restarts / max_task_retries still travel as ray_remote_args (deprecated, no named form)
            warnings.filterwarnings("ignore", message=".*ray_remote_args.*is deprecated")
            return self._build_dataset(items, resources, isolate)

    def _build_dataset(self, items: list[dict], resources: dict, isolate: bool):
        import ray

        from pipeline.onboard.engines.ray_workers import RenderWorker, StepWorker, step_groups

        opts = self.cfg.ray
        # a crashed actor is replaced (on a surviving node if its node died); the batch it held is not
        # retried on it (a restarting actor on a dead node only fails it again): it is dropped from the
        # round, and the driver re-submits its meshes in the next round (_stream)
        retry = {"max_restarts": -1, "max_task_retries": 0}
        steps = [s for s in self.run_spec.downstream if any(s.key in r["todo"] for r in items)]
        groups = step_groups(steps)  # one actor pool each
        n_caption = sum(opts.caption_actors for g in groups if _captioner_pool(g[0]))
        n_embed = sum(opts.embed_actors for g in groups if not _captioner_pool(g[0]))
        source = self.run_spec.source.key
        n_render = sum(source in r["todo"] for r in items)
        cpus, gpus = resources.get("CPU", 1.0), resources.get("GPU", 0.0)
        layout = plan_layout(opts, cpus, gpus, n_caption, n_embed, n_render)
        logging.getLogger(__name__).info("ray layout: %s", layout.describe())
        self.layout = layout

        table = pa.Table.from_pylist(items, schema=row_schema(self.run_spec))
        step = 1 if isolate else max(1, opts.render_batch_size)
        ds = ray.data.from_arrow([table.slice(i, step) for i in range(0, table.num_rows, step)])
        common = {"batch_format": "pyarrow", "zero_copy_batch": True, **retry}
        ds = ds.map_batches(
            RenderWorker,
            fn_constructor_args=(self.run_spec, self.run_id, n_render > 0, self.library_root),
            batch_size=step,
            compute=_pool(layout.render_workers),
            num_cpus=layout.render_cpus,
            **common,
        )
        for g in groups:
            big = _captioner_pool(g[0])
            ds = ds.map_batches(
                StepWorker,
                fn_constructor_args=(self.run_spec, self.run_id, tuple(s.key for s in g), g is groups[-1]),
                batch_size=1 if isolate else (opts.caption_batch_size if big else opts.embed_batch_size),
                compute=_pool(opts.caption_actors if big else opts.embed_actors),
                num_cpus=layout.model_cpus,
                num_gpus=(layout.caption_gpus if big else layout.embed_gpus) or None,
                **common,
            )
        return ds

    # ------------------------------------------------------------------ committing
    def _commit_rows(self, plan: Plan, rows: list[dict], bars, summary: RunSummary) -> None:
        """Commit a batch of finished meshes exactly as the local engine commits its batches."""
        for name, column in timing_columns(self.run_spec).items():
            total = sum(r[column] or 0.0 for r in rows)
            if total:
                self.seconds[name] = self.seconds.get(name, 0.0) + total
        source = self.run_spec.source
        rendered = [r for r in rows if source.key in r["todo"]]
        if rendered:
            source_out = pa.concat_tables([unpack(r[source.key]) for r in rendered])
            meshes_rows = []
            for r in rendered:
                first = unpack(r[source.key]).slice(0, 1).to_pylist()
                meshes_rows.extend(self.rendered_mesh_rows(plan, r["mesh_id"], first))
                summary.rendered += first[0].get("error") is None
            bars[source.stage.name].update(len(rendered))
            summary.failed += self.commit_batch(plan, source_out, meshes_rows, bars, _computed(rendered))
        stored = [r for r in rows if source.key not in r["todo"]]
        if stored:
            ids = pa.table({"mesh_id": pa.array([r["mesh_id"] for r in stored], pa.string())})
            summary.failed += self.commit_batch(plan, ids, [], bars, _computed(stored))

    def _commit_lost(self, plan: Plan, lost: list[dict]) -> int:
        """Errors rows (and failed meshes rows) for meshes whose batch failed every retry."""
        now = utcnow()
        paths = {f.mesh_id: f.source_path for f in plan.files}
        reason = (
            f"killed its Ray worker {MESH_STRIKES} times, the last time alone in its batch, with no node "
            f"lost meanwhile (crash or out of memory; see the Ray logs, {log_dir()})"
        )
        errors, meshes_rows = [], []
        for r in lost:
            # charged to the first step the mesh needed
            step = next((s for s in self.run_spec.steps if s.key in r["todo"]), self.run_spec.steps[-1])
            errors.append(
                {
                    "run_id": self.run_id,
                    "stage": step.stage.name,
                    "mesh_id": r["mesh_id"],
                    "source_path": paths.get(r["mesh_id"]),
                    "fingerprint": step.fingerprint,
                    "error_type": "WorkerCrash",
                    "reason": reason,
                    "at": now,
                }
            )
            if step is self.run_spec.source:
                meshes_rows.extend(self.rendered_mesh_rows(plan, r["mesh_id"], [{"error": reason}]))
        tables = {"errors": pa.Table.from_pylist(errors, schema=schemas.ERRORS)}
        if meshes_rows:
            tables["meshes"] = pa.Table.from_pylist(meshes_rows, schema=schemas.MESHES)
        self.store.commit(tables, self.run_id)
        return len(lost)


def end_executor_loops(threads: list, timeout_s: float = EXECUTOR_JOIN_S) -> None:
    """Ask Ray Data's executor loops of an aborted round to stop at their next step and wait briefly, so
    that ``ray.shutdown()`` does not pull the connection from under a loop blocked in ``ray.wait`` (Ray
    then ends that thread with ``SystemExit``, which Python's thread hook drops but test runners report).
    Ray Data has no public way to stop a dataset whose iterator is blocked in another thread; its
    executor's own ``shutdown`` also tears down the operators, which can block on a lost cluster, so only
    its loop's stop flag is set (``StreamingExecutor._shutdown``, checked after every scheduling step)."""
    for t in threads:
        if hasattr(t, "_shutdown"):
            t._shutdown = True
    deadline = time.monotonic() + timeout_s
    for t in threads:
        t.join(timeout=max(deadline - time.monotonic(), 0.0))


def _captioner_pool(step: Step) -> bool:
    """The captioner (the big model) has its own pool options; every encoder uses the embed options."""
    return step.role == "captioner"


def _computed(rows: list[dict]):
    """``outputs`` for :meth:`Engine.commit_batch`: the steps' outputs the actors computed for these
    meshes, as the stage objects returned them (the stages are not run again in the driver)."""

    def outputs(step: Step, mesh_ids: list[str], make_input) -> pa.Table:
        tables = [t for r in rows if (t := unpack(r.get(step.key))) is not None]
        out = pa.concat_tables(tables) if tables else None
        missing = set(mesh_ids) - (set(out.column("mesh_id").to_pylist()) if out is not None else set())
        if missing:
            raise RuntimeError(
                f"{step.key}: no computed rows for {len(missing)} mesh(es), e.g. {min(missing)}"
            )
        return out.filter(pc.field("mesh_id").isin(mesh_ids))

    return outputs


def _pool(size: int):
    """A fixed pool of ``size`` actors, one batch at a time each: when an actor crashes, only the batch
    it was running is retried (a queued batch would die with it and spend its retries too)."""
    from ray.data import ActorPoolStrategy

    return ActorPoolStrategy(size=max(1, size), max_tasks_in_flight_per_actor=1)


def _setup_error(exc: Exception) -> Exception:
    """The one-line error a worker's setup failure deserves (a missing model weight, no OpenGL), if the
    Ray error wraps one; else ``exc`` itself."""
    import re

    from pipeline.models.registry import ModelLoadError
    from pipeline.onboard.engines.render_pool import RenderSetupError

    for cls in (ModelLoadError, RenderSetupError, LibraryUnreachableError):
        found = re.search(rf"{cls.__name__}: (.+)", str(exc))
        if found:
            return cls(found.group(1).strip())
    return exc


def _start_ray(opts: RayOptions) -> bool:
    """Connect to (or start) Ray; return True if this call started it (and should shut it down)."""
    try:
        import ray
    except ImportError:
        raise RayEngineError(
            "--engine ray needs Ray Data: pip install 'oscar-pipeline[ray]' (or pip install 'ray[data]')"
        ) from None
    if ray.is_initialized():
        return False
    # ERROR: not the notices of a routine start (token authentication on a private instance, ...)
    kwargs: dict = {"include_dashboard": False, "logging_level": logging.ERROR, "log_to_driver": False}
    kwargs["address"] = "local"  # a private instance, even where `ray start` left a cluster running
    if opts.address:
        import pipeline

        # ship this checkout's package to the cluster so workers run the driver's code
        kwargs["runtime_env"] = {"py_modules": [str(Path(pipeline.__file__).parent)]}
        kwargs["address"] = opts.address
    if opts.num_cpus and not opts.address:
        kwargs["num_cpus"] = opts.num_cpus
    try:
        with quiet_driver_core():
            ray.init(**kwargs)
    except Exception as exc:  # unreachable cluster, bad address
        where = opts.address or "a local instance"
        raise RayEngineError(f"cannot start Ray on {where}: {type(exc).__name__}: {exc}") from exc
    from pipeline.onboard.supervise import note_ray_logs

    note_ray_logs(log_dir())
    return True

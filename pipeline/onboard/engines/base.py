"""What every engine shares: planning and committing.

An engine runs the steps of a :class:`~pipeline.onboard.config.RunSpec` over a
:class:`~pipeline.onboard.plan.Plan`. Subclasses decide where the steps' outputs are computed (the
local engine in this process and its render workers, the Ray engine on a Ray cluster); this class
plans the run, commits what discovery found, and commits each batch of finished meshes, so that both
engines write exactly the same rows.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import pyarrow as pa
import pyarrow.compute as pc

from pipeline import schemas
from pipeline.onboard.config import RunSpec
from pipeline.onboard.guard import RemovalGuardError, check_removals
from pipeline.onboard.interrupt import RunInterrupted, StopFlag
from pipeline.onboard.plan import Plan, make_plan
from pipeline.onboard.stages import STAGE_NAMES, Step, decoded
from pipeline.onboard.stages.base import split_errors
from pipeline.store import Store, utcnow

GEOMETRY_COLUMNS = ("n_vertices", "n_faces", "bounds_min", "bounds_max", "units_guess", "scale_to_unit")

#: ``outputs(step, mesh_ids, make_input)``: the step's output rows for these meshes of a batch
StepOutputs = Callable[[Step, list[str], Callable[[], pa.Table]], pa.Table]


@dataclass
class RunSummary:
    """What a run did; printed at the end and stored in ``runs``."""

    run_id: str
    n_files: int = 0
    added: int = 0
    removed: int = 0
    skipped: int = 0
    failed: int = 0
    failed_before: int = 0
    hashed: int = 0
    rendered: int = 0
    captioned: int = 0
    seconds: dict[str, float] = field(default_factory=dict)
    total_seconds: float = 0.0
    status: str = "ok"
    restored: int = 0  # of ``added``: files whose mesh was onboarded before (not rendered again)
    resumed: int = 0  # meshes already in the store with stages left (shown only when some are)
    removal_guard: dict = field(default_factory=dict)  # the guard's record (pipeline.onboard.guard)
    guard_line: str = ""
    warnings: list[str] = field(default_factory=list)
    lost_nodes: list[str] = field(default_factory=list)  # Ray nodes lost during the run
    redone: int = 0  # meshes re-submitted after their batch was lost (a lost node, a crashed worker)

    def to_dict(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k != "guard_line"}

    def lines(self) -> list[str]:
        rate = self.rendered / self.total_seconds if self.total_seconds > 0 else 0.0
        stages = ", ".join(f"{k} {v:.1f}s" for k, v in self.seconds.items())
        back = f" ({self.restored} onboarded before, not rendered again)" if self.restored else ""
        lines = [
            f"run {self.run_id}: {self.n_files} files, {self.added} added{back}, {self.removed} removed, "
            f"{self.skipped} unchanged, "
            + (f"{self.resumed} with stages left, " if self.resumed else "")
            + f"{self.failed} failed"
            + (
                f" ({self.failed_before} failed before, skipped; --retry-failed retries them)"
                if self.failed_before
                else ""
            ),
            f"rendered {self.rendered} meshes, captioned {self.captioned}; {self.total_seconds:.1f}s total "
            f"({rate:.2f} meshes/s); {stages}",
        ] + self.cluster_lines()
        return lines + ([self.guard_line] if self.guard_line else [])

    def cluster_lines(self) -> list[str]:
        """What the cluster lost and what was redone (nothing when nothing was lost)."""
        if not (self.lost_nodes or self.redone):
            return []
        nodes = ", ".join(self.lost_nodes)
        lost = f"lost Ray node(s) {nodes}" if nodes else "lost Ray worker(s), no node"
        return [f"{lost}: {self.redone} meshes redone on the surviving workers (not counted as failed)"]

    def cluster(self) -> dict:
        """The ``cluster`` entry of the run's ``runs`` row."""
        return {"lost_nodes": list(self.lost_nodes), "meshes_redone": self.redone}


class Timer:
    """Adds the seconds spent in a ``with`` block to ``seconds[name]``."""

    def __init__(self, seconds: dict[str, float], name: str):
        self.seconds, self.name = seconds, name

    def __enter__(self) -> None:
        self.t = time.perf_counter()

    def __exit__(self, *exc) -> None:
        self.seconds[self.name] = self.seconds.get(self.name, 0.0) + time.perf_counter() - self.t


def progress_bars(progress: bool, run: RunSpec, plan: Plan) -> dict:
    """One bar per stage, sized by the meshes that need any of its steps: tqdm bars on a terminal, plain
    per-stage lines in a cron log (:mod:`pipeline.progress`)."""
    from pipeline.progress import stage_bars

    totals = {name: set() for name in STAGE_NAMES}
    for step in run.steps:
        totals[step.stage.name] |= plan.todo.get(step.key, set())
    return stage_bars({k: len(ids) for k, ids in totals.items()}, unit="mesh", enabled=progress)


class Engine:
    """Plans a run and commits its batches; subclasses compute the steps' outputs (:meth:`run`)."""

    #: whether :meth:`commit_batch` leaves a batch's remaining steps to the next run on a stop request
    #: (True where the steps are computed there, as in the local engine)
    STOP_BETWEEN_STEPS = True

    def __init__(self, store: Store, run: RunSpec, run_id: str, progress: bool = True):
        self.store, self.run_spec, self.cfg, self.run_id, self.progress = (
            store,
            run,
            run.cfg,
            run_id,
            progress,
        )
        self.seconds: dict[str, float] = {}
        self.summary: RunSummary | None = None  # set by :meth:`begin`: the counts so far, if the run stops
        self.stop = StopFlag()  # set on SIGINT/SIGTERM (pipeline.onboard.interrupt); read between steps
        self.kept_complete: set[str] = set()  # meshes committed with every step this run had for them
        self.kept_partial: set[str] = set()  # meshes committed with some steps left (a stop request)
        self.planned: set[str] = set()  # meshes this run has work for
        self.done: dict[str, int] = {}  # stage name -> meshes it processed

    def run(self, library: str) -> RunSummary:
        """Onboard ``library``: plan, compute, commit batch by batch; the run's summary."""
        raise NotImplementedError

    # ------------------------------------------------------------------ start and end of a run
    def begin(self, library: str) -> tuple[Plan, RunSummary]:
        """Plan the run, commit what discovery found, and start the summary."""
        summary = self.summary = RunSummary(self.run_id)
        with Timer(self.seconds, "discover"):
            plan = make_plan(self.store, library, self.run_spec)
        summary.n_files = len(plan.files) + len(plan.discover_errors)
        summary.hashed = plan.n_hashed
        guard = check_removals(
            plan.n_active_before,
            plan.n_vanished,
            summary.n_files,
            self.cfg.max_removed,
            self.cfg.allow_removal,
        )
        summary.removal_guard, summary.guard_line = guard.describe(), guard.line()
        if guard.tripped:  # nothing is committed: the run's record counts no change
            raise RemovalGuardError(guard, plan.library_root, summary)
        summary.skipped = plan.skipped
        summary.resumed = plan.resumed
        summary.failed_before = plan.failed_before
        summary.removed = len(plan.removed_rows)
        summary.added = sum(len(v) for v in plan.new_paths.values())
        summary.restored = plan.restored
        summary.failed += len(plan.discover_errors)
        if summary.n_files == 0:
            summary.warnings.append(
                f"library {plan.library_root} holds no mesh file (.obj/.ply/.glb/.gltf/.stl/.off): nothing to do"
            )
        self._commit_discovery(plan)
        self.planned = set().union(*plan.todo.values())
        return plan, summary

    def left(self) -> int:
        """Meshes this run had work for that it has not committed with all their steps."""
        return len(self.planned - (self.kept_complete - self.kept_partial))

    def interrupted(self, signum: int) -> RunInterrupted:
        """The error of a run stopped by ``signum``, with how many meshes it kept and left."""
        complete = self.kept_complete - self.kept_partial
        kept = complete | self.kept_partial
        return RunInterrupted(signum, len(kept), len(complete), self.left(), self.summary)

    def finish(self, summary: RunSummary, t0: float) -> RunSummary:
        summary.captioned = self.done.get("caption", 0)
        summary.seconds = {k: round(v, 3) for k, v in self.seconds.items()}
        summary.total_seconds = round(time.perf_counter() - t0, 3)
        return summary

    # ------------------------------------------------------------------ discovery
    def _commit_discovery(self, plan: Plan) -> None:
        """Commit vanished/replaced files, discovery errors and rows for already-rendered new paths."""
        tables: dict[str, pa.Table] = {}
        now = utcnow()
        rows = [{**r, "seen_at": now, "run_id": self.run_id} for r in plan.removed_rows]
        render_set = set(plan.render)
        missing_geo = [m for m in plan.new_paths if m not in render_set]
        if missing_geo:
            known = self._known_geometry(missing_geo)
            failed_render = {m for m in missing_geo if m not in known}
            for m in missing_geo:
                for f in plan.new_paths[m]:
                    status = "failed" if m in failed_render else "active"
                    rows.append(self._mesh_row(plan, f, known.get(m, {}), status, now))
        if rows:
            tables["meshes"] = pa.Table.from_pylist(rows, schema=schemas.MESHES)
        errs = self._new_discovery_errors(plan, now)
        if errs:
            tables["errors"] = pa.Table.from_pylist(errs, schema=schemas.ERRORS)
        self.store.commit(tables, self.run_id)

    def _known_geometry(self, mesh_ids: list[str]) -> dict[str, dict]:
        t = self.store.read(
            "meshes", filter=pc.field("mesh_id").isin(mesh_ids) & pc.field("n_faces").is_valid()
        )
        return {r["mesh_id"]: {k: r[k] for k in GEOMETRY_COLUMNS} for r in t.to_pylist()}

    def _new_discovery_errors(self, plan: Plan, now) -> list[dict]:
        old = self.store.read("errors", columns=["stage", "source_path", "reason"])
        seen = set(zip(old.column("source_path").to_pylist(), old.column("reason").to_pylist(), strict=True))
        return [
            {
                "run_id": self.run_id,
                "stage": "discover",
                "mesh_id": None,
                "source_path": f.source_path,
                "fingerprint": None,
                "error_type": "DiscoveryError",
                "reason": reason,
                "at": now,
            }
            for f, reason in plan.discover_errors
            if (f.source_path, reason) not in seen
        ]

    def _mesh_row(self, plan: Plan, f, geo: dict, status: str, now) -> dict:
        return {
            "mesh_id": f.mesh_id,
            "source_path": f.source_path,
            "library_root": plan.library_root,
            "name": f.name,
            "format": f.format,
            "file_size": f.size,
            "mtime_ns": f.mtime_ns,
            "deps": f.deps,
            **geo,
            "status": status,
            "seen_at": now,
            "run_id": self.run_id,
        }

    def rendered_mesh_rows(self, plan: Plan, mesh_id: str, rows: list[dict]) -> list[dict]:
        """``meshes`` rows for the new paths of a mesh just rendered (``rows``: its render output)."""
        now = utcnow()
        ok = rows[0].get("error") is None
        geo = {k: rows[0].get(k) for k in GEOMETRY_COLUMNS} if ok else {}
        return [
            self._mesh_row(plan, f, geo, "active" if ok else "failed", now)
            for f in plan.new_paths.get(mesh_id, [])
        ]

    # ------------------------------------------------------------------ batches
    def stored_rows(self, step: Step, mesh_ids: list[str]) -> pa.Table:
        """The latest stored output of ``step`` for these meshes, by mesh and view."""
        flt = pc.field("mesh_id").isin(mesh_ids) & (pc.field("fingerprint") == step.fingerprint)
        t = self.store.read_latest(step.dataset, filter=flt)
        return t.sort_by([("mesh_id", "ascending"), ("view_index", "ascending")])

    def commit_batch(
        self, plan: Plan, source_out: pa.Table, meshes_rows: list[dict], bars, outputs: StepOutputs
    ) -> int:
        """Run the later steps over one batch and commit every table; return the number of failed meshes.

        ``source_out`` is the first step's output for the batch (rendered now, with error rows, or read
        from the store); ``outputs(step, mesh_ids, make_input)`` gives each later step's output for the
        meshes that need it (computed here from ``make_input()``, or by another engine)."""
        paths = {f.mesh_id: f.source_path for f in plan.files}
        source = self.run_spec.source
        tables: dict[str, pa.Table] = {}
        errors: list[pa.Table] = []
        failed: set[str] = set()
        if "error" in source_out.column_names:
            rows, errs = split_errors(
                source_out, source.stage.target(source_out), source.stage.name, self.run_id, paths
            )
            errors.append(errs)
            failed |= set(errs.column("mesh_id").to_pylist())
            tables[source.dataset] = rows
        else:
            rows = source_out
        batch = {source.key: rows}  # this batch's output of each step, as stored
        ids = list(dict.fromkeys(rows.column("mesh_id").to_pylist()))

        counted: dict[str, set[str]] = {}
        stopped = False
        with decoded.batch_scope():  # the batch's stages decode each view once
            for step in self.run_spec.downstream:
                step_ids = [m for m in ids if m in plan.todo[step.key] and m not in failed]
                if not step_ids:
                    continue
                if self.stop.requested and self.STOP_BETWEEN_STEPS:  # keep what is finished; the rest waits
                    stopped = True
                    break
                out = outputs(step, step_ids, lambda s=step, i=step_ids: self._input(s, batch, i))
                rows, errs = split_errors(out, step.stage.target(out), step.stage.name, self.run_id, paths)
                errors.append(errs)
                failed |= set(errs.column("mesh_id").to_pylist())
                tables[step.dataset] = rows
                batch[step.key] = rows
                new = set(step_ids) - counted.setdefault(step.stage.name, set())
                counted[step.stage.name] |= new
                bars[step.stage.name].update(len(new))
                self.done[step.stage.name] = self.done.get(step.stage.name, 0) + len(new)

        if meshes_rows:
            tables["meshes"] = pa.Table.from_pylist(meshes_rows, schema=schemas.MESHES)
        errs = [e for e in errors if e.num_rows]
        if errs:
            tables["errors"] = pa.concat_tables(errs)
        with Timer(self.seconds, "commit"):
            self.store.commit(tables, self.run_id)
        (self.kept_partial if stopped else self.kept_complete).update(ids)
        return len(failed)

    def _input(self, step: Step, batch: dict[str, pa.Table], mesh_ids: list[str]) -> pa.Table:
        """The input rows of ``step`` for these meshes: this batch's output of its input step, plus
        stored rows for meshes whose input was not produced in this batch."""
        made = batch.get(step.input)
        src = made.filter(pc.field("mesh_id").isin(mesh_ids)) if made is not None else None
        done = set(made.column("mesh_id").to_pylist()) if made is not None else set()
        stored = [m for m in mesh_ids if m not in done]
        if stored:
            more = self.stored_rows(self.run_spec.step(step.input), stored)
            src = more if src is None else pa.concat_tables([src, more])
        return src

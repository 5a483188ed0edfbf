"""The Ray engine's workers: the onboarding stages wrapped as Ray Data ``map_batches`` callables.

A row of the Ray dataset is one mesh. What each step produces for it travels in one Arrow IPC blob per
step, in the column named by the step's key (``render``, ``caption``, ``embed_text``,
``embed_image:<role>``), so every stage object receives exactly the table it receives in the local
engine and returns exactly what it returns there; the driver unpacks the blobs and commits them through
the same code as the local engine. Which steps a mesh needs was decided by the planner (the ``todo``
column); a mesh that failed a step skips the later ones, as in the local engine.
"""

from __future__ import annotations

import contextlib
import io
import os
import time
from pathlib import Path

import pyarrow as pa
import pyarrow.compute as pc

from pipeline import schemas
from pipeline.onboard.config import RunSpec
from pipeline.onboard.stages import STAGE_NAMES, Step

#: seconds spent reading stored inputs (the other timings are per stage, ``t_<stage>``)
LOAD_TIMING = "t_load"


def timing_columns(run: RunSpec) -> dict[str, str]:
    """Timing name -> its column: per-mesh seconds in each stage (a batch's time split evenly over the
    meshes it processed), and in loading stored inputs."""
    names = list(STAGE_NAMES)
    names.insert(1, "load")
    return {n: f"t_{n}" for n in names}


def input_keys(run: RunSpec) -> list[str]:
    """Keys of the steps whose output some later step reads (stored rows are shipped for these)."""
    return list(dict.fromkeys(s.input for s in run.steps if s.input is not None))


def part_column(key: str) -> str:
    """Column naming the store part that holds a mesh's stored output of step ``key``."""
    return f"part:{key}"


def stored_column(key: str) -> str:
    """Column holding a mesh's stored output of step ``key`` (read by the render actor)."""
    return f"stored:{key}"


def row_schema(run: RunSpec) -> pa.Schema:
    """Schema of the Ray dataset: one row per mesh, one output blob per step of the run."""
    blob = pa.large_binary()
    inputs = input_keys(run)
    return pa.schema(
        [
            ("mesh_id", pa.string()),
            ("abs_path", pa.string()),
            ("format", pa.string()),
            ("todo", pa.list_(pa.string())),  # keys of the steps this mesh needs
            *[(part_column(k), pa.string()) for k in inputs],
            *[(s.key, blob) for s in run.steps],
            *[(stored_column(k), blob) for k in inputs],
            *[(c, pa.float64()) for c in timing_columns(run).values()],
        ]
    )


def pack(table: pa.Table) -> bytes:
    """Arrow IPC stream bytes of ``table``."""
    sink = io.BytesIO()
    with pa.ipc.new_stream(sink, table.schema) as writer:
        writer.write_table(table)
    return sink.getvalue()


def unpack(blob: bytes | None) -> pa.Table | None:
    """The table packed by :func:`pack` (``None`` stays ``None``)."""
    if blob is None:
        return None
    return pa.ipc.open_stream(pa.py_buffer(blob)).read_all()


def by_mesh(table: pa.Table) -> dict[str, pa.Table]:
    """Rows of ``table`` per ``mesh_id``, in their original order."""
    ids = table.column("mesh_id").to_pylist()
    groups: dict[str, list[int]] = {}
    for i, m in enumerate(ids):
        groups.setdefault(m, []).append(i)
    return {m: table.take(idx) for m, idx in groups.items()}


def has_error(table: pa.Table | None) -> bool:
    return table is not None and "error" in table.column_names and pc.any(pc.is_valid(table["error"])).as_py()


def failed_so_far(row: dict, run: RunSpec) -> bool:
    """Whether any step already run for this mesh produced an error row (later steps skip it)."""
    return any(has_error(unpack(row[s.key])) for s in run.steps)


class _Fault:
    """Test hook (``RayOptions.inject_fault``): kill this actor process on a given mesh."""

    def __init__(self, spec: str, stage: str):
        parts = spec.split(":", 2) if spec else []
        self.active = len(parts) == 3 and parts[0] == stage
        self.prefix, self.marker = (parts[1], parts[2]) if self.active else ("", "")

    def maybe_crash(self, rows: list[dict]) -> None:
        if not self.active or not any(r["mesh_id"].startswith(self.prefix) for r in rows):
            return
        if self.marker:
            if Path(self.marker).exists():
                return
            Path(self.marker).touch()
        os._exit(17)


class _Pause:
    """Test hook (``RayOptions.pause_at``): on the first batch holding a given mesh at a given stage,
    write this actor's Ray node id to a file and wait there (up to a minute) for the test to kill the
    node, so that a node dies at a known point of the run rather than after a guessed sleep."""

    def __init__(self, spec: str, stage: str):
        parts = spec.split(":", 2) if spec else []
        self.active = len(parts) == 3 and parts[0] == stage
        self.prefix, self.marker = (parts[1], Path(parts[2])) if self.active else ("", None)

    def maybe_wait(self, rows: list[dict]) -> None:
        if not self.active or not any(r["mesh_id"].startswith(self.prefix) for r in rows):
            return
        import ray

        try:
            with open(self.marker, "x") as f:  # the first attempt only
                f.write(ray.get_runtime_context().get_node_id())
        except FileExistsError:
            return
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            time.sleep(0.05)


class _Worker:
    """Common batch plumbing: rows in, the same rows with this stage's blob and timing filled, out."""

    def __init__(self, run: RunSpec, run_id: str, step: Step, final: bool = False):
        self.run, self.run_id, self.step, self.final = run, run_id, step, final
        self.cfg = run.cfg
        self.schema = row_schema(run)
        self.timing = f"t_{step.stage.name}"
        self._fault = _Fault(run.cfg.ray.inject_fault, step.stage.name)
        self._pause = _Pause(run.cfg.ray.pause_at, step.stage.name)

    def __call__(self, batch: pa.Table) -> pa.Table:
        rows = batch.to_pylist()
        self.process_batch(rows)
        if self.final:  # stored inputs are not needed by the driver: do not ship them back
            for r in rows:
                for k in input_keys(self.run):
                    r[stored_column(k)] = None
        return pa.Table.from_pylist(rows, schema=self.schema)

    def process_batch(self, rows: list[dict]) -> None:
        """Run this worker's step on the rows (a worker of several steps runs each in turn)."""
        _timed(rows, self._fault, self._pause, self.timing, lambda: self.process(rows))

    def process(self, rows: list[dict]) -> list[dict]:
        """Fill this step's blob of the rows that need it; return those rows (timed here)."""
        raise NotImplementedError


def _timed(rows: list[dict], fault: _Fault, pause: _Pause, timing: str, work) -> None:
    """The test hooks of one stage, then ``work()``, whose seconds are split over the rows it returns."""
    fault.maybe_crash(rows)
    pause.maybe_wait(rows)
    t0 = time.perf_counter()
    done = work()
    if done:
        share = (time.perf_counter() - t0) / len(done)
        for r in done:
            r[timing] = (r.get(timing) or 0.0) + share


class RenderWorker(_Worker):
    """Renders meshes (one GL context in one child process per actor, with the per-mesh timeout of
    ``cfg.render_timeout_s``) and loads the stored inputs of meshes that are not re-rendered."""

    def __init__(self, run: RunSpec, run_id: str, render: bool, library_root: str | None = None):
        super().__init__(run, run_id, run.source)
        self._pool = self._stage = None
        if render and library_root:  # a node that cannot see the library fails here, not mesh by mesh
            from pipeline.onboard.engines.ray_cluster import (
                LibraryUnreachableError,
                this_node,
                unreachable_message,
                unreadable,
            )

            why = unreadable(library_root)
            if why:
                raise LibraryUnreachableError(unreachable_message(this_node(), "library", library_root, why))
        if render:  # start the GL context now: a worker without OpenGL fails here, not mesh by mesh
            if self.cfg.workers > 0:
                from pipeline.onboard.engines.render_pool import RenderPool

                self._pool = RenderPool(self.cfg, run_id, 1, self.cfg.render_timeout_s, self.step)
            else:
                self._stage = self.step.stage.runner(self.cfg, run_id, self.step)

    def process(self, rows: list[dict]) -> list[dict]:
        from pipeline.onboard.stages.render import RENDER_OUT

        key = self.step.key
        self._load_stored([r for r in rows if key not in r["todo"]])
        todo = [r for r in rows if key in r["todo"]]
        by_id = {r["mesh_id"]: r for r in todo}
        items = [{"mesh_id": r["mesh_id"], "abs_path": r["abs_path"], "format": r["format"]} for r in todo]
        t = time.perf_counter()
        for item, out in self._render(items):
            row = by_id[item["mesh_id"]]
            row[key] = pack(pa.Table.from_pylist(out, schema=RENDER_OUT))
            now = time.perf_counter()
            row[self.timing], t = now - t, now
        return []  # timings are per mesh already

    def _render(self, items: list[dict]):
        if self._pool is not None:
            yield from self._pool.map(items)
        else:
            for it in items:
                yield it, self._stage.render_one(it)

    def _load_stored(self, rows: list[dict]) -> None:
        """Read, from the store parts the driver located, the stored inputs these meshes need."""
        t0 = time.perf_counter()
        for key in input_keys(self.run):
            step = self.run.step(key)
            parts: dict[str, list[dict]] = {}
            for r in rows:
                if r[part_column(key)]:
                    parts.setdefault(r[part_column(key)], []).append(r)
            for part, rs in parts.items():
                got = by_mesh(_read_part(part, [r["mesh_id"] for r in rs], step.fingerprint, step.dataset))
                for r in rs:
                    if r["mesh_id"] in got:
                        r[stored_column(key)] = pack(got[r["mesh_id"]])
        if rows:
            for r in rows:
                r[LOAD_TIMING] = (time.perf_counter() - t0) / len(rows)


def _read_part(part: str, mesh_ids: list[str], fingerprint: str, table: str) -> pa.Table:
    import pyarrow.dataset as ds

    from pipeline.store import latest_rows

    flt = pc.field("mesh_id").isin(mesh_ids) & (pc.field("fingerprint") == fingerprint)
    t = ds.dataset(part, format="parquet", schema=schemas.TABLES[table]).to_table(filter=flt)
    t = latest_rows(t, list(schemas.KEYS[table]))
    return t.sort_by([("mesh_id", "ascending"), ("view_index", "ascending")])


class StepWorker(_Worker):
    """Runs one step, or several consecutive steps that read the same input with the same model
    (:func:`step_groups`), over the meshes that need them: their input is this run's output of the input
    step, else the stored one. The model is built once, when the actor starts; the steps of a group run
    inside one :func:`~pipeline.onboard.stages.decoded.batch_scope`, as the local engine's batch does, so
    each view is decoded once and what one step keeps for the next (the learned encoder's object patch
    tokens, from the pass that embeds the views) is not computed again."""

    def __init__(self, run: RunSpec, run_id: str, keys: tuple[str, ...], final: bool = False):
        steps = [run.step(k) for k in keys]
        super().__init__(run, run_id, steps[0], final)
        self.steps = steps
        first = steps[0].stage.runner(self.cfg, run_id, steps[0])
        model = first.model  # load the model when the actor starts, not inside the first batch
        self.runners = [first, *(s.stage.runner(self.cfg, run_id, s, model=model) for s in steps[1:])]
        ray_opts = run.cfg.ray
        self._hooks = [(_Fault(ray_opts.inject_fault, s.stage.name), _Pause(ray_opts.pause_at, s.stage.name)) for s in steps]

    def process_batch(self, rows: list[dict]) -> None:
        from pipeline.onboard.stages import decoded

        # a single step sees each view once: nothing to share, so no images held for the batch
        with decoded.batch_scope() if len(self.steps) > 1 else contextlib.nullcontext():
            for step, runner, (fault, pause) in zip(self.steps, self.runners, self._hooks, strict=True):
                _timed(rows, fault, pause, f"t_{step.stage.name}", lambda s=step, f=runner: self._run(s, f, rows))

    def _run(self, step: Step, runner, rows: list[dict]) -> list[dict]:
        todo = []
        for r in rows:
            if step.key not in r["todo"] or failed_so_far(r, self.run):
                continue
            src = self._input(step, r)
            if src is not None and src.num_rows:
                todo.append((r, src))
        if not todo:
            return []
        out = by_mesh(runner(pa.concat_tables([s for _, s in todo])))
        for r, _ in todo:
            r[step.key] = pack(out[r["mesh_id"]])
        return [r for r, _ in todo]

    def _input(self, step: Step, row: dict) -> pa.Table | None:
        """The mesh's input rows as ``step`` takes them (``None``: neither made now nor stored)."""
        made = unpack(row[step.input])
        if made is not None:
            return schemas.conform(made, self.run.step(step.input).stage.target(made))
        return unpack(row[stored_column(step.input)])


def step_groups(steps: list[Step]) -> list[list[Step]]:
    """``steps`` (in run order) cut into the groups one :class:`StepWorker` runs: consecutive steps that read
    the same input with the same model spec share one actor (one model copy; in the offline profile the
    learned encoder's ``embed_image``, probe and patch steps), every other step has its own."""
    groups: list[list[Step]] = []
    for s in steps:
        last = groups[-1][0] if groups else None
        if last is not None and s.spec is not None and (s.input, s.role, s.spec) == (last.input, last.role, last.spec):
            groups[-1].append(s)
        else:
            groups.append([s])
    return groups

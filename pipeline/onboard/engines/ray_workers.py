"""The Ray engine's workers: the onboarding stages wrapped as Ray Data ``map_batches`` callables.

A row of the Ray dataset is one mesh. What each stage produces for it travels in one Arrow IPC blob per
stage (``views``, ``caption``, ``embed_text``, ``embed_image:<role>``), so every stage object receives
exactly the table it receives in the local executor and returns exactly what it returns there; the
driver unpacks the blobs and commits them through the local executor's code. Which stages a mesh needs
was decided by the planner (``do_*`` columns); a mesh that failed a stage skips the later ones, as in
the local executor.
"""

from __future__ import annotations

import io
import os
import time
from pathlib import Path

import pyarrow as pa
import pyarrow.compute as pc

from pipeline import schemas
from pipeline.onboard.config import OnboardConfig

#: per-mesh seconds spent in each stage (a batch's time split evenly over the meshes it processed)
TIMING_COLUMNS = ("t_render", "t_load", "t_caption", "t_embed_text", "t_embed_image")
#: blobs read from the store for meshes that are not rendered in this run (dropped before the driver)
STORED_COLUMNS = ("stored_views", "stored_captions")


def row_schema(roles: list[str]) -> pa.Schema:
    """Schema of the Ray dataset: one row per mesh; ``roles`` are the image encoder roles of the run."""
    blob = pa.large_binary()
    return pa.schema(
        [
            ("mesh_id", pa.string()),
            ("abs_path", pa.string()),
            ("format", pa.string()),
            ("do_render", pa.bool_()),
            ("do_caption", pa.bool_()),
            ("do_text", pa.bool_()),
            ("image_roles", pa.list_(pa.string())),
            ("views_part", pa.string()),  # store part holding the mesh's views (meshes not rendered now)
            ("captions_part", pa.string()),  # store part holding its captions (text-only work)
            ("views", blob),
            ("stored_views", blob),
            ("stored_captions", blob),
            ("caption", blob),
            ("embed_text", blob),
            *[(f"embed_image:{r}", blob) for r in roles],
            *[(c, pa.float64()) for c in TIMING_COLUMNS],
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


def failed_so_far(row: dict) -> bool:
    """Whether any stage already run for this mesh produced an error row (later stages skip it)."""
    outputs = [c for c in row if c in ("views", "caption", "embed_text") or c.startswith("embed_image:")]
    return any(has_error(unpack(row[c])) for c in outputs)


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


class _Worker:
    """Common batch plumbing: rows in, the same rows with this stage's blob and timing filled, out."""

    stage = ""
    timing = ""

    def __init__(self, cfg: OnboardConfig, run_id: str, roles: list[str], final: bool = False):
        self.cfg, self.run_id, self.roles, self.final = cfg, run_id, roles, final
        self.schema = row_schema(roles)
        self._fault = _Fault(cfg.ray.inject_fault, self.stage)

    def __call__(self, batch: pa.Table) -> pa.Table:
        rows = batch.to_pylist()
        self._fault.maybe_crash(rows)
        t0 = time.perf_counter()
        done = self.process(rows)
        if done and self.timing:
            share = (time.perf_counter() - t0) / len(done)
            for r in done:
                r[self.timing] = (r.get(self.timing) or 0.0) + share
        if self.final:  # stored inputs are not needed by the driver: do not ship them back
            for r in rows:
                for c in STORED_COLUMNS:
                    r[c] = None
        return pa.Table.from_pylist(rows, schema=self.schema)

    def process(self, rows: list[dict]) -> list[dict]:
        """Fill this stage's blob of the rows that need it; return those rows."""
        raise NotImplementedError


def _views_input(row: dict) -> pa.Table | None:
    """The mesh's views as the downstream stages take them (``None``: not rendered or render failed)."""
    rendered = unpack(row["views"])
    if rendered is not None:
        if has_error(rendered):
            return None
        return schemas.conform(rendered, schemas.VIEWS)
    return unpack(row["stored_views"])


class RenderWorker(_Worker):
    """Renders meshes (one GL context in one child process per actor, with the per-mesh timeout of
    ``cfg.render_timeout_s``) and loads the stored views/captions of meshes that are not re-rendered."""

    stage = "render"
    timing = "t_render"

    def __init__(self, cfg: OnboardConfig, run_id: str, roles: list[str], fps: dict[str, str], render: bool):
        super().__init__(cfg, run_id, roles)
        self.fps = fps
        self._pool = self._stage = None
        if render:  # start the GL context now: a worker without OpenGL fails here, not mesh by mesh
            if cfg.workers > 0:
                from pipeline.onboard.engines.render_pool import RenderPool

                self._pool = RenderPool(cfg, run_id, 1, cfg.render_timeout_s)
            else:
                from pipeline.onboard.stages import RenderStage

                self._stage = RenderStage(cfg, run_id)

    def process(self, rows: list[dict]) -> list[dict]:
        from pipeline.onboard.stages import RENDER_OUT

        self._load_stored([r for r in rows if not r["do_render"]])
        todo = [r for r in rows if r["do_render"]]
        by_id = {r["mesh_id"]: r for r in todo}
        items = [{"mesh_id": r["mesh_id"], "abs_path": r["abs_path"], "format": r["format"]} for r in todo]
        t = time.perf_counter()
        for item, out in self._render(items):
            row = by_id[item["mesh_id"]]
            row["views"] = pack(pa.Table.from_pylist(out, schema=RENDER_OUT))
            now = time.perf_counter()
            row["t_render"], t = now - t, now
        return []  # timings are per mesh already

    def _render(self, items: list[dict]):
        if self._pool is not None:
            yield from self._pool.map(items)
        else:
            for it in items:
                yield it, self._stage.render_one(it)

    def _load_stored(self, rows: list[dict]) -> None:
        """Read, from the store parts the driver located, the views and captions these meshes need."""
        t0 = time.perf_counter()
        for column, part_column, fp_key, key in (
            ("stored_views", "views_part", "render", "views"),
            ("stored_captions", "captions_part", "caption", "captions"),
        ):
            parts: dict[str, list[dict]] = {}
            for r in rows:
                if r[part_column]:
                    parts.setdefault(r[part_column], []).append(r)
            for part, rs in parts.items():
                got = by_mesh(_read_part(part, [r["mesh_id"] for r in rs], self.fps[fp_key], key))
                for r in rs:
                    if r["mesh_id"] in got:
                        r[column] = pack(got[r["mesh_id"]])
        if rows:
            for r in rows:
                r["t_load"] = (time.perf_counter() - t0) / len(rows)


def _read_part(part: str, mesh_ids: list[str], fingerprint: str, table: str) -> pa.Table:
    import pyarrow.dataset as ds

    from pipeline.store import latest_rows

    flt = pc.field("mesh_id").isin(mesh_ids) & (pc.field("fingerprint") == fingerprint)
    t = ds.dataset(part, format="parquet", schema=schemas.TABLES[table]).to_table(filter=flt)
    t = latest_rows(t, list(schemas.KEYS[table]))
    return t.sort_by([("mesh_id", "ascending"), ("view_index", "ascending")])


class CaptionWorker(_Worker):
    """Captions the views of the meshes that need it, a batch at a time (one captioner per actor)."""

    stage = "caption"
    timing = "t_caption"

    def __init__(self, cfg: OnboardConfig, run_id: str, roles: list[str], final: bool = False):
        super().__init__(cfg, run_id, roles, final)
        from pipeline.onboard.stages import CaptionStage

        self.step = CaptionStage(cfg, run_id)
        _ = self.step.model  # load the model when the actor starts, not inside the first batch

    def process(self, rows: list[dict]) -> list[dict]:
        todo = [(r, v) for r in rows if r["do_caption"] and (v := _views_input(r)) is not None]
        if not todo:
            return []
        out = by_mesh(self.step(pa.concat_tables([v for _, v in todo])))
        for r, _ in todo:
            r["caption"] = pack(out[r["mesh_id"]])
        return [r for r, _ in todo]


class TextEmbedWorker(_Worker):
    """Embeds the captions of the meshes that need it: this run's captions, else the stored ones."""

    stage = "embed_text"
    timing = "t_embed_text"

    def __init__(self, cfg: OnboardConfig, run_id: str, roles: list[str], final: bool = False):
        super().__init__(cfg, run_id, roles, final)
        from pipeline.onboard.stages import TextEmbedStage

        self.step = TextEmbedStage(cfg, run_id)
        _ = self.step.model

    def process(self, rows: list[dict]) -> list[dict]:
        todo = []
        for r in rows:
            if not r["do_text"] or failed_so_far(r):
                continue
            fresh = unpack(r["caption"])
            src = (
                schemas.conform(fresh, schemas.CAPTIONS)
                if fresh is not None
                else unpack(r["stored_captions"])
            )
            if src is not None and src.num_rows:
                todo.append((r, src))
        if not todo:
            return []
        out = by_mesh(self.step(pa.concat_tables([s for _, s in todo])))
        for r, _ in todo:
            r["embed_text"] = pack(out[r["mesh_id"]])
        return [r for r, _ in todo]


class ImageEmbedWorker(_Worker):
    """Embeds the views of the meshes that need it with one image encoder role."""

    stage = "embed_image"
    timing = "t_embed_image"

    def __init__(self, cfg: OnboardConfig, run_id: str, roles: list[str], role: str, final: bool = False):
        super().__init__(cfg, run_id, roles, final)
        from pipeline.onboard.stages import ImageEmbedStage

        self.role = role
        self.step = ImageEmbedStage(cfg, run_id, role)
        _ = self.step.model

    def process(self, rows: list[dict]) -> list[dict]:
        todo = []
        for r in rows:
            if self.role not in (r["image_roles"] or []) or failed_so_far(r):
                continue
            views = _views_input(r)
            if views is not None:
                todo.append((r, views))
        if not todo:
            return []
        out = by_mesh(self.step(pa.concat_tables([v for _, v in todo])))
        for r, _ in todo:
            r[f"embed_image:{self.role}"] = pack(out[r["mesh_id"]])
        return [r for r, _ in todo]

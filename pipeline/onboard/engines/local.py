"""The local executor: runs the onboarding stages in-process (rendering in worker processes), batch by
batch, committing each batch's rows of every table atomically."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from dataclasses import dataclass, field

import pyarrow as pa
import pyarrow.compute as pc

from pipeline import schemas
from pipeline.onboard.config import OnboardConfig
from pipeline.onboard.plan import Plan, encoder_slugs, make_plan
from pipeline.onboard.stages import CaptionStage, ImageEmbedStage, RenderStage, TextEmbedStage, split_errors
from pipeline.onboard.stages.render import RENDER_OUT
from pipeline.store import Store, new_run_id, utcnow

GEOMETRY_COLUMNS = ("n_vertices", "n_faces", "bounds_min", "bounds_max", "units_guess", "scale_to_unit")


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

    def to_dict(self) -> dict:
        return dict(self.__dict__)

    def lines(self) -> list[str]:
        rate = self.rendered / self.total_seconds if self.total_seconds > 0 else 0.0
        stages = ", ".join(f"{k} {v:.1f}s" for k, v in self.seconds.items())
        return [
            f"run {self.run_id}: {self.n_files} files, {self.added} added, {self.removed} removed, "
            f"{self.skipped} unchanged, {self.failed} failed"
            + (
                f" ({self.failed_before} failed before, skipped; --retry-failed retries them)"
                if self.failed_before
                else ""
            ),
            f"rendered {self.rendered} meshes, captioned {self.captioned}; {self.total_seconds:.1f}s total "
            f"({rate:.2f} meshes/s); {stages}",
        ]


class _Timer:
    def __init__(self, seconds: dict[str, float], name: str):
        self.seconds, self.name = seconds, name

    def __enter__(self):
        self.t = time.perf_counter()

    def __exit__(self, *exc):
        self.seconds[self.name] = self.seconds.get(self.name, 0.0) + time.perf_counter() - self.t


def _bars(progress: bool, plan: Plan):
    """Per-stage progress: tqdm bars on a terminal, plain lines in a cron log (:mod:`pipeline.progress`)."""
    from pipeline.progress import stage_bars

    totals = {
        "render": len(plan.render),
        "caption": len(plan.caption),
        "embed_text": len(plan.embed_text),
        "embed_image": len(set().union(*plan.embed_image.values())) if plan.embed_image else 0,
    }
    return stage_bars(totals, unit="mesh", enabled=progress)


def _prefetch(source: Iterator, maxsize: int) -> Iterator:
    """Drain ``source`` in a thread so render workers keep busy while this thread captions and embeds."""
    import queue
    import threading

    q: queue.Queue = queue.Queue(maxsize=max(1, maxsize))
    stop = threading.Event()
    done = object()

    def pump() -> None:
        try:
            for item in source:
                while not stop.is_set():
                    try:
                        q.put(("item", item), timeout=0.2)
                        break
                    except queue.Full:
                        continue
                if stop.is_set():
                    return
            q.put(("end", done))
        except BaseException as exc:  # re-raised in the consumer
            q.put(("error", exc))

    t = threading.Thread(target=pump, name="render-prefetch", daemon=True)
    t.start()
    try:
        while True:
            kind, value = q.get()
            if kind == "end":
                return
            if kind == "error":
                raise value
            yield value
    finally:
        stop.set()
        t.join(timeout=5)


class LocalExecutor:
    """Runs a :class:`Plan` in this process; models are built once and reused across batches."""

    def __init__(self, store: Store, cfg: OnboardConfig, run_id: str, progress: bool = True, models=None):
        self.store, self.cfg, self.run_id, self.progress = store, cfg, run_id, progress
        models = models or {}
        self.caption = CaptionStage(cfg, run_id, model=models.get("captioner"))
        self.text = TextEmbedStage(cfg, run_id, model=models.get("text_encoder"))
        self.images = {r: ImageEmbedStage(cfg, run_id, r, model=models.get(r)) for r in cfg.image_roles()}
        self.text_slug, self.image_slugs = encoder_slugs(cfg)
        self.seconds: dict[str, float] = {}
        self.captioned = 0
        self.fps = cfg.fingerprints()

    # ------------------------------------------------------------------ run
    def _begin(self, library: str) -> tuple[Plan, RunSummary]:
        """Plan the run, commit what discovery found, and start the summary (shared by every engine)."""
        summary = RunSummary(self.run_id)
        with _Timer(self.seconds, "discover"):
            plan = make_plan(self.store, library, self.cfg, self.text_slug, self.image_slugs)
        summary.n_files = len(plan.files) + len(plan.discover_errors)
        summary.hashed = plan.n_hashed
        summary.skipped = plan.skipped
        summary.failed_before = plan.failed_before
        summary.removed = len(plan.removed_rows)
        summary.added = sum(len(v) for v in plan.new_paths.values())
        summary.failed += len(plan.discover_errors)
        self._commit_discovery(plan)
        return plan, summary

    def _finish(self, summary: RunSummary, t0: float) -> RunSummary:
        summary.captioned = self.captioned
        summary.seconds = {k: round(v, 3) for k, v in self.seconds.items()}
        summary.total_seconds = round(time.perf_counter() - t0, 3)
        return summary

    def run(self, library: str) -> RunSummary:
        t0 = time.perf_counter()
        plan, summary = self._begin(library)
        self._load_models(plan)
        bars = _bars(self.progress, plan)
        try:
            for views, meshes_rows in self._rendered_batches(plan, bars["render"], summary):
                summary.failed += self._downstream(plan, views, meshes_rows, bars)
            ids = plan.downstream_ids()
            for i in range(0, len(ids), self.cfg.batch_size):
                chunk = ids[i : i + self.cfg.batch_size]
                with _Timer(self.seconds, "load_views"):
                    views = self._stored_views(chunk)
                summary.failed += self._downstream(plan, views, [], bars)
        finally:
            for b in bars.values():
                b.close()
        return self._finish(summary, t0)

    def _load_models(self, plan: Plan) -> None:
        """Build the models this run needs before any rendering, so a missing weight fails fast."""
        with _Timer(self.seconds, "model_load"):
            if plan.caption:
                _ = self.caption.model
            if plan.embed_text:
                _ = self.text.model
            for role, stage in self.images.items():
                if plan.embed_image.get(role):
                    _ = stage.model

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

    # ------------------------------------------------------------------ rendering
    def _render_stream(self, items: list[dict]) -> Iterator[tuple[dict, list[dict]]]:
        if self.cfg.workers <= 0:
            stage = RenderStage(self.cfg, self.run_id)
            for it in items:
                yield it, stage.render_one(it)
            return
        from pipeline.onboard.engines.render_pool import RenderPool

        t0 = time.perf_counter()
        pool = RenderPool(self.cfg, self.run_id, min(self.cfg.workers, len(items)), self.cfg.render_timeout_s)
        try:
            yield from _prefetch(pool.map(items), maxsize=2 * self.cfg.batch_size)
        finally:
            pool.close()
            # wall time of the render pool, start-up included; "render" is the main thread's wait for it
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
        pending_rows: list[dict] = []
        pending_meshes: list[dict] = []
        n_in_batch = 0
        t = time.perf_counter()
        for item, rows in self._render_stream(items):
            bar.update(1)
            pending_rows.extend(rows)
            pending_meshes.extend(self._rendered_mesh_rows(plan, item["mesh_id"], rows))
            n_in_batch += 1
            summary.rendered += rows[0].get("error") is None
            if n_in_batch >= self.cfg.batch_size:
                self.seconds["render"] = self.seconds.get("render", 0.0) + time.perf_counter() - t
                yield pa.Table.from_pylist(pending_rows, schema=RENDER_OUT), pending_meshes
                pending_rows, pending_meshes, n_in_batch = [], [], 0
                t = time.perf_counter()
        self.seconds["render"] = self.seconds.get("render", 0.0) + time.perf_counter() - t
        if n_in_batch:
            yield pa.Table.from_pylist(pending_rows, schema=RENDER_OUT), pending_meshes

    def _rendered_mesh_rows(self, plan: Plan, mesh_id: str, rows: list[dict]) -> list[dict]:
        now = utcnow()
        ok = rows[0].get("error") is None
        geo = {k: rows[0].get(k) for k in GEOMETRY_COLUMNS} if ok else {}
        return [
            self._mesh_row(plan, f, geo, "active" if ok else "failed", now)
            for f in plan.new_paths.get(mesh_id, [])
        ]

    def _stored_views(self, mesh_ids: list[str]) -> pa.Table:
        flt = pc.field("mesh_id").isin(mesh_ids) & (pc.field("fingerprint") == self.fps["render"])
        t = self.store.read_latest("views", filter=flt)
        return t.sort_by([("mesh_id", "ascending"), ("view_index", "ascending")])

    # ------------------------------------------------------------------ downstream
    def _downstream(
        self, plan: Plan, render_out: pa.Table, meshes_rows: list[dict], bars, computed: dict | None = None
    ) -> int:
        """Caption and embed one batch of views; commit everything; return the number of failed meshes.

        ``computed`` holds stage outputs another engine already computed for this batch (``caption``,
        ``embed_text``, ``embed_image:<role>``, as the stages return them); the stages are then not run
        here, but the same meshes are selected and the same rows committed."""
        paths = {f.mesh_id: f.source_path for f in plan.files}
        tables: dict[str, pa.Table] = {}
        errors: list[pa.Table] = []
        failed: set[str] = set()
        if "error" in render_out.column_names:
            views, errs = split_errors(render_out, schemas.VIEWS, "render", self.run_id, paths)
            errors.append(errs)
            failed |= set(errs.column("mesh_id").to_pylist())
            tables["views"] = views
        else:
            views = render_out
        ids = list(dict.fromkeys(views.column("mesh_id").to_pylist()))

        cap_ids = [m for m in ids if m in plan.caption]
        captions = None
        if cap_ids:
            out = self._stage_output(
                "caption",
                self.caption,
                cap_ids,
                lambda: views.filter(pc.field("mesh_id").isin(cap_ids)),
                computed,
            )
            captions, errs = split_errors(out, schemas.CAPTIONS, "caption", self.run_id, paths)
            errors.append(errs)
            failed |= set(errs.column("mesh_id").to_pylist())
            tables["captions"] = captions
            bars["caption"].update(len(cap_ids))
            self.captioned += len(cap_ids)

        txt_ids = [m for m in ids if m in plan.embed_text and m not in failed]
        if txt_ids:
            out = self._stage_output(
                "embed_text", self.text, txt_ids, lambda: self._text_input(captions, txt_ids), computed
            )
            emb, errs = split_errors(
                out, schemas.embedding_schema(_vector_dim(out)), "embed_text", self.run_id, paths
            )
            errors.append(errs)
            failed |= set(errs.column("mesh_id").to_pylist())
            tables[f"text_embeddings/{self.text_slug}"] = emb
            bars["embed_text"].update(len(txt_ids))

        img_done: set[str] = set()
        for role, stage in self.images.items():
            img_ids = [m for m in ids if m in plan.embed_image.get(role, ()) and m not in failed]
            if not img_ids:
                continue
            out = self._stage_output(
                f"embed_image:{role}",
                stage,
                img_ids,
                lambda ids=img_ids: views.filter(pc.field("mesh_id").isin(ids)),
                computed,
            )
            emb, errs = split_errors(
                out, schemas.embedding_schema(_vector_dim(out)), "embed_image", self.run_id, paths
            )
            errors.append(errs)
            failed |= set(errs.column("mesh_id").to_pylist())
            tables[f"image_embeddings/{self.image_slugs[role]}"] = emb
            img_done |= set(img_ids)
        bars["embed_image"].update(len(img_done))

        if meshes_rows:
            tables["meshes"] = pa.Table.from_pylist(meshes_rows, schema=schemas.MESHES)
        errs = [e for e in errors if e.num_rows]
        if errs:
            tables["errors"] = pa.concat_tables(errs)
        with _Timer(self.seconds, "commit"):
            self.store.commit(tables, self.run_id)
        return len(failed)

    def _stage_output(self, key: str, stage, ids: list[str], make_input, computed: dict | None) -> pa.Table:
        """``stage(make_input())``, timed; or the rows of ``ids`` in ``computed[key]`` (another engine's)."""
        if computed is None:
            with _Timer(self.seconds, key.split(":")[0]):
                return stage(make_input())
        out = computed.get(key)
        missing = set(ids) - (set(out.column("mesh_id").to_pylist()) if out is not None else set())
        if missing:
            raise RuntimeError(f"{key}: no computed rows for {len(missing)} mesh(es), e.g. {min(missing)}")
        return out.filter(pc.field("mesh_id").isin(ids))

    def _text_input(self, captions: pa.Table | None, txt_ids: list[str]) -> pa.Table:
        """Captions to embed: this batch's, plus stored ones for meshes not captioned in this batch."""
        src = captions.filter(pc.field("mesh_id").isin(txt_ids)) if captions is not None else None
        done = set(captions.column("mesh_id").to_pylist()) if captions is not None else set()
        stored = [m for m in txt_ids if m not in done]
        if stored:
            more = self._stored_captions(stored)
            src = more if src is None else pa.concat_tables([src, more])
        return src

    def _stored_captions(self, mesh_ids: list[str]) -> pa.Table:
        flt = pc.field("mesh_id").isin(mesh_ids) & (pc.field("fingerprint") == self.fps["caption"])
        return self.store.read_latest("captions", filter=flt)


def _vector_dim(stage_out: pa.Table) -> int:
    """Vector width of an embedding stage's output (its schema fixes it; no model needed)."""
    return stage_out.schema.field("embedding").type.list_size


def run_onboarding(
    library: str,
    store_path: str,
    cfg: OnboardConfig,
    *,
    progress: bool = True,
    models: dict | None = None,
) -> RunSummary:
    """Onboard ``library`` into the store at ``store_path``; returns the run's summary."""
    store = Store.open(store_path, create=True, writable=True)
    run_id = new_run_id()
    started = utcnow()
    summary = RunSummary(run_id, status="interrupted")
    try:
        if cfg.engine == "ray":
            from pipeline.onboard.engines.ray import RayExecutor

            summary = RayExecutor(store, cfg, run_id, progress=progress).run(library)
        else:
            summary = LocalExecutor(store, cfg, run_id, progress=progress, models=models).run(library)
        summary.status = "ok"
    finally:
        row = {
            "run_id": run_id,
            "engine": cfg.engine,
            "library_root": str(library),
            "profile": cfg.profile,
            "config_json": json.dumps(cfg.describe(), default=str),
            "started_at": started,
            "finished_at": utcnow(),
            "n_files": summary.n_files,
            "n_added": summary.added,
            "n_removed": summary.removed,
            "n_skipped": summary.skipped,
            "n_failed": summary.failed,
            "stage_seconds_json": json.dumps(summary.seconds),
            "status": summary.status,
        }
        store.commit({"runs": pa.Table.from_pylist([row], schema=schemas.RUNS)}, run_id)
        store.close()
    return summary

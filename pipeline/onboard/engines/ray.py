"""The Ray engine (``--engine ray``): the onboarding stages on Ray Data, committed by the driver.

The driver plans exactly as the local executor does (:func:`pipeline.onboard.plan.make_plan`), streams one row
per mesh through ``map_batches`` stages (render actors on CPUs, then captioner and encoder actor pools,
on GPUs where the cluster has them) and commits every ``cfg.batch_size`` finished meshes through the
local executor's own code (``LocalExecutor._downstream``). Only the driver writes the store, so the
parts, keys and fingerprints are those of the local engine: either engine can continue the other's
work. A crashed actor is restarted and its batch retried (``RayOptions.max_retries``); a batch that
still fails becomes ``errors`` rows (WorkerCrash) and the run goes on.
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
from pipeline.onboard.config import OnboardConfig
from pipeline.onboard.engines.local import LocalExecutor, RunSummary, _bars, _Timer
from pipeline.onboard.engines.ray_options import RayOptions
from pipeline.onboard.engines.ray_workers import TIMING_COLUMNS, row_schema, unpack
from pipeline.onboard.plan import Plan
from pipeline.store import Store, utcnow


class RayEngineError(RuntimeError):
    """The Ray engine cannot run (Ray missing, cluster unreachable, every batch failed)."""


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


class RayExecutor(LocalExecutor):
    """Runs a :class:`Plan` on Ray Data; models live in the actors, never in the driver."""

    def __init__(self, store: Store, cfg: OnboardConfig, run_id: str, progress: bool = True):
        super().__init__(store, cfg, run_id, progress=progress)
        self.roles = cfg.image_roles()
        self.layout: Layout | None = None

    # ------------------------------------------------------------------ run
    def run(self, library: str) -> RunSummary:
        t0 = time.perf_counter()
        plan, summary = self._begin(library)
        items = self._items(plan)
        if items:
            bars = _bars(self.progress, plan)
            try:
                with _Timer(self.seconds, "ray_start"):
                    started = _start_ray(self.cfg.ray)
                try:
                    self._run_dataset(plan, items, bars, summary)
                finally:
                    if started:
                        import ray

                        ray.shutdown()
            finally:
                for b in bars.values():
                    b.close()
        return self._finish(summary, t0)

    # ------------------------------------------------------------------ inputs
    def _items(self, plan: Plan) -> list[dict]:
        """One row per mesh with work: what to render, which stages it needs, where stored inputs are."""
        first_file = plan.file_of()
        rows = []
        for m in plan.render:
            f = first_file[m]
            rows.append(self._item(plan, m, abs_path=f.abs_path, fmt=f.format, render=True))
        stored = plan.downstream_ids()
        rows_stored = [self._item(plan, m) for m in stored]
        need_views = [r["mesh_id"] for r in rows_stored if r["do_caption"] or r["image_roles"]]
        need_caps = [r["mesh_id"] for r in rows_stored if r["do_text"] and not r["do_caption"]]
        views_at = self._locate("views", self.fps["render"], need_views)
        caps_at = self._locate("captions", self.fps["caption"], need_caps)
        for r in rows_stored:
            r["views_part"] = views_at.get(r["mesh_id"])
            r["captions_part"] = caps_at.get(r["mesh_id"])
        return rows + rows_stored

    def _item(self, plan: Plan, mesh_id: str, abs_path=None, fmt=None, render=False) -> dict:
        return {
            "mesh_id": mesh_id,
            "abs_path": abs_path,
            "format": fmt,
            "do_render": render,
            "do_caption": mesh_id in plan.caption,
            "do_text": mesh_id in plan.embed_text,
            "image_roles": [r for r in self.roles if mesh_id in plan.embed_image.get(r, ())],
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
        return {m: str(Path(p).resolve()) for m, (_, p) in best.items()}

    # ------------------------------------------------------------------ the dataset
    def _run_dataset(self, plan: Plan, items: list[dict], bars, summary: RunSummary) -> None:
        import ray.data

        ctx = ray.data.DataContext.get_current()
        saved = (ctx.max_errored_blocks, ctx.enable_progress_bars, ctx.print_on_execution_start)
        ctx.max_errored_blocks = -1  # a batch that still fails after retries becomes errors rows
        ctx.enable_progress_bars = False
        ctx.print_on_execution_start = False
        ctx.execution_options.preserve_order = False
        logging.getLogger("ray.data").setLevel(logging.WARNING)
        try:
            self._stream(plan, items, bars, summary)
        finally:
            ctx.max_errored_blocks, ctx.enable_progress_bars, ctx.print_on_execution_start = saved

    def _stream(self, plan: Plan, items: list[dict], bars, summary: RunSummary) -> None:
        import ray

        ds = self._dataset(items, ray.cluster_resources())
        sent = {r["mesh_id"]: r for r in items}
        received: set[str] = set()
        try:
            for batch in ds.iter_batches(batch_size=self.cfg.batch_size, batch_format="pyarrow"):
                rows = batch.to_pylist()
                received |= {r["mesh_id"] for r in rows}
                self._commit_rows(plan, rows, bars, summary)
        except ray.exceptions.RayError as exc:
            setup = _setup_error(exc)
            if setup is exc:
                raise
            raise setup from exc
        lost = [sent[m] for m in sent if m not in received]
        if lost:
            if not received:
                raise RayEngineError(
                    f"every batch failed on the Ray cluster ({len(lost)} meshes); see the Ray logs "
                    "(`ray logs` or /tmp/ray/session_latest/logs)"
                )
            summary.failed += self._commit_lost(plan, lost)

    def _dataset(self, items: list[dict], resources: dict):
        """The Ray Data pipeline: render/load actors, then captioner and encoder actor pools."""
        with warnings.catch_warnings():
            # max_restarts / max_task_retries still travel as ray_remote_args (deprecated, no named form)
            warnings.filterwarnings("ignore", message=".*ray_remote_args.*is deprecated")
            return self._build_dataset(items, resources)

    def _build_dataset(self, items: list[dict], resources: dict):
        import ray

        from pipeline.onboard.engines.ray_workers import (
            CaptionWorker,
            ImageEmbedWorker,
            RenderWorker,
            TextEmbedWorker,
        )

        opts = self.cfg.ray
        # a crashed actor is always replaced; the batch it held is retried max_retries times, then dropped
        # (and recorded as errors rows by the driver) so one poisonous batch cannot stall the pool
        retry = {"max_restarts": -1, "max_task_retries": opts.max_retries}
        need_caption = any(r["do_caption"] for r in items)
        need_text = any(r["do_text"] for r in items)
        roles = [role for role in self.roles if any(role in r["image_roles"] for r in items)]
        n_caption = opts.caption_actors if need_caption else 0
        n_embed = opts.embed_actors * (need_text + len(roles))
        n_render = sum(r["do_render"] for r in items)
        cpus, gpus = resources.get("CPU", 1.0), resources.get("GPU", 0.0)
        layout = plan_layout(opts, cpus, gpus, n_caption, n_embed, n_render)
        logging.getLogger(__name__).info("ray layout: %s", layout.describe())
        self.layout = layout
        stages = [s for s, on in (("caption", need_caption), ("text", need_text)) if on] + roles
        last = stages[-1] if stages else None

        schema = row_schema(self.roles)
        table = pa.Table.from_pylist(items, schema=schema)
        step = max(1, opts.render_batch_size)
        ds = ray.data.from_arrow([table.slice(i, step) for i in range(0, table.num_rows, step)])
        common = {"batch_format": "pyarrow", "zero_copy_batch": True, **retry}
        ds = ds.map_batches(
            RenderWorker,
            fn_constructor_args=(self.cfg, self.run_id, self.roles, self.fps, n_render > 0),
            batch_size=step,
            compute=_pool(layout.render_workers),
            num_cpus=layout.render_cpus,
            **common,
        )
        captioner = {"num_cpus": layout.model_cpus, "num_gpus": layout.caption_gpus or None, **common}
        encoder = {"num_cpus": layout.model_cpus, "num_gpus": layout.embed_gpus or None, **common}
        if need_caption:
            ds = ds.map_batches(
                CaptionWorker,
                fn_constructor_args=(self.cfg, self.run_id, self.roles, last == "caption"),
                batch_size=opts.caption_batch_size,
                compute=_pool(opts.caption_actors),
                **captioner,
            )
        if need_text:
            ds = ds.map_batches(
                TextEmbedWorker,
                fn_constructor_args=(self.cfg, self.run_id, self.roles, last == "text"),
                batch_size=opts.embed_batch_size,
                compute=_pool(opts.embed_actors),
                **encoder,
            )
        for role in roles:
            ds = ds.map_batches(
                ImageEmbedWorker,
                fn_constructor_args=(self.cfg, self.run_id, self.roles, role, last == role),
                batch_size=opts.embed_batch_size,
                compute=_pool(opts.embed_actors),
                **encoder,
            )
        return ds

    # ------------------------------------------------------------------ committing
    def _commit_rows(self, plan: Plan, rows: list[dict], bars, summary: RunSummary) -> None:
        """Commit a batch of finished meshes exactly as the local executor commits its batches."""
        for name in TIMING_COLUMNS:
            stage = name[2:]
            total = sum(r[name] or 0.0 for r in rows)
            if total:
                self.seconds[stage] = self.seconds.get(stage, 0.0) + total
        rendered = [r for r in rows if r["do_render"]]
        if rendered:
            render_out = pa.concat_tables([unpack(r["views"]) for r in rendered])
            meshes_rows = []
            for r in rendered:
                first = unpack(r["views"]).slice(0, 1).to_pylist()
                meshes_rows.extend(self._rendered_mesh_rows(plan, r["mesh_id"], first))
                summary.rendered += first[0].get("error") is None
            bars["render"].update(len(rendered))
            summary.failed += self._downstream(plan, render_out, meshes_rows, bars, self._computed(rendered))
        stored = [r for r in rows if not r["do_render"]]
        if stored:
            ids = pa.table({"mesh_id": pa.array([r["mesh_id"] for r in stored], pa.string())})
            summary.failed += self._downstream(plan, ids, [], bars, self._computed(stored))

    def _computed(self, rows: list[dict]) -> dict[str, pa.Table]:
        """Stage outputs of these meshes, per stage, as the stage objects returned them."""
        out: dict[str, pa.Table] = {}
        for key in ["caption", "embed_text"] + [f"embed_image:{r}" for r in self.roles]:
            tables = [t for r in rows if (t := unpack(r.get(key))) is not None]
            if tables:
                out[key] = pa.concat_tables(tables)
        return out

    def _commit_lost(self, plan: Plan, lost: list[dict]) -> int:
        """Errors rows (and failed meshes rows) for meshes whose batch failed every retry."""
        now = utcnow()
        paths = {f.mesh_id: f.source_path for f in plan.files}
        reason = (
            f"lost on the Ray cluster: its batch failed {self.cfg.ray.max_retries + 1} times "
            "(worker crash or out of memory; see the Ray logs)"
        )
        errors, meshes_rows = [], []
        for r in lost:
            stage = next(
                s
                for s, on in (
                    ("render", r["do_render"]),
                    ("caption", r["do_caption"]),
                    ("embed_text", r["do_text"]),
                    ("embed_image", True),
                )
                if on
            )
            fp_key = stage if stage != "embed_image" else f"embed_image:{(r['image_roles'] or self.roles)[0]}"
            errors.append(
                {
                    "run_id": self.run_id,
                    "stage": stage,
                    "mesh_id": r["mesh_id"],
                    "source_path": paths.get(r["mesh_id"]),
                    "fingerprint": self.fps[fp_key],
                    "error_type": "WorkerCrash",
                    "reason": reason,
                    "at": now,
                }
            )
            if r["do_render"]:
                meshes_rows.extend(self._rendered_mesh_rows(plan, r["mesh_id"], [{"error": reason}]))
        tables = {"errors": pa.Table.from_pylist(errors, schema=schemas.ERRORS)}
        if meshes_rows:
            tables["meshes"] = pa.Table.from_pylist(meshes_rows, schema=schemas.MESHES)
        self.store.commit(tables, self.run_id)
        return len(lost)


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

    for cls in (ModelLoadError, RenderSetupError):
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
    kwargs: dict = {"include_dashboard": False, "logging_level": logging.WARNING, "log_to_driver": False}
    if opts.address:
        import pipeline

        # ship this checkout's package to the cluster so workers run the driver's code
        kwargs["runtime_env"] = {"py_modules": [str(Path(pipeline.__file__).parent)]}
        kwargs["address"] = opts.address
    elif opts.num_cpus:
        kwargs["num_cpus"] = opts.num_cpus
    try:
        ray.init(**kwargs)
    except Exception as exc:  # unreachable cluster, bad address
        where = opts.address or "a local instance"
        raise RayEngineError(f"cannot start Ray on {where}: {type(exc).__name__}: {exc}") from exc
    return True

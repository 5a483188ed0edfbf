"""One onboarding run: resolve the config once, pick the engine, record the run in ``runs``."""

from __future__ import annotations

import json

import pyarrow as pa

from pipeline import schemas
from pipeline.onboard.config import OnboardConfig, RunSpec
from pipeline.onboard.engines.base import Engine, RunSummary
from pipeline.onboard.engines.local import LocalEngine
from pipeline.store import Store, new_run_id, utcnow


def make_engine(store: Store, spec: RunSpec, run_id: str, progress: bool, models: dict | None) -> Engine:
    """The engine ``--engine`` names (Ray is imported only when chosen: it is optional)."""
    if spec.cfg.engine == "ray":
        from pipeline.onboard.engines.ray import RayEngine

        return RayEngine(store, spec, run_id, progress=progress)
    return LocalEngine(store, spec, run_id, progress=progress, models=models)


def run_onboarding(
    library: str,
    store_path: str,
    cfg: OnboardConfig,
    *,
    progress: bool = True,
    models: dict | None = None,
) -> RunSummary:
    """Onboard ``library`` into the store at ``store_path``; returns the run's summary.

    ``models`` (role -> adapter) replaces the profile's models in the local engine (tests)."""
    spec = cfg.resolve()  # the profile and fingerprints, once for the whole run
    store = Store.open(store_path, create=True, writable=True)
    run_id = new_run_id()
    started = utcnow()
    summary = RunSummary(run_id, status="interrupted")
    try:
        summary = make_engine(store, spec, run_id, progress, models).run(library)
        summary.status = "ok"
    finally:
        row = {
            "run_id": run_id,
            "engine": cfg.engine,
            "library_root": str(library),
            "profile": cfg.profile,
            "config_json": json.dumps({**spec.describe(), "cluster": summary.cluster()}, default=str),
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
        try:
            if summary.status == "ok":
                from pipeline.compact import auto_compact

                auto_compact(store, run_id)  # tables whose small files piled up; the run's row still last
            store.commit({"runs": pa.Table.from_pylist([row], schema=schemas.RUNS)}, run_id)
        except Exception:
            if summary.status == "ok":  # the run's own error (if any) is the one to report
                raise
        finally:
            store.close()
    return summary

"""One onboarding run: resolve the config once, pick the engine, record the run in ``runs``."""

from __future__ import annotations

import json

import pyarrow as pa

from pipeline import schemas
from pipeline.onboard.config import OnboardConfig, RunSpec
from pipeline.onboard.engines.base import Engine, RunSummary
from pipeline.onboard.engines.local import LocalEngine
from pipeline.onboard.guard import RemovalGuardError
from pipeline.onboard.interrupt import RunInterrupted, StopFlag, StopRequested, stop_on_signals
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
    flag = StopFlag()
    with stop_on_signals(flag):
        return _run(library, store_path, cfg, spec, flag, progress, models)


def _run(
    library: str, store_path: str, cfg: OnboardConfig, spec: RunSpec, flag: StopFlag, progress: bool, models
) -> RunSummary:
    store = Store.open(store_path, create=True, writable=True)
    run_id = new_run_id()
    started = utcnow()
    summary = RunSummary(run_id, status="interrupted")
    engine: Engine | None = None
    try:
        engine = make_engine(store, spec, run_id, progress, models)
        engine.stop = flag
        flag.check()
        summary = engine.run(library)
        if flag.requested and engine.left():  # it ended early on the stop request: not finished
            raise StopRequested(flag.signum)
        _refit_adapter(store, spec, run_id, summary, progress)
        summary.status = "ok"
    except RemovalGuardError as exc:
        summary = _status(exc.summary or summary, "refused", engine)
        raise
    except StopRequested as exc:
        summary = _status(engine and engine.summary or summary, "interrupted", engine)
        if engine is None:
            raise RunInterrupted(exc.args[0], 0, 0, 0, summary) from None
        raise engine.interrupted(exc.args[0]) from None
    except KeyboardInterrupt:
        summary = _status(engine and engine.summary or summary, "interrupted", engine)
        raise
    except BaseException:
        summary = _status(engine and engine.summary or summary, "failed", engine)
        raise
    finally:
        config = {**spec.describe(), "cluster": summary.cluster()}
        if summary.removal_guard:
            config["removal_guard"] = {**config["removal_guard"], **summary.removal_guard}
        row = {
            "run_id": run_id,
            "engine": cfg.engine,
            "library_root": str(library),
            "profile": cfg.profile,
            "config_json": json.dumps(config, default=str),
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


def _refit_adapter(store: Store, spec: RunSpec, run_id: str, summary: RunSummary, progress: bool) -> None:
    """Refit the store's query adapter when this run changed what it is fitted on (:mod:`pipeline.adapter`)."""
    import sys
    import time

    from pipeline.adapter.table import refresh

    t0 = time.perf_counter()
    fitted = refresh(store, spec, run_id, log=lambda msg: print(msg, file=sys.stderr))
    summary.seconds["adapter"] = round(time.perf_counter() - t0, 3)
    if fitted and progress:
        print(
            f"query adapter fitted on {fitted['n_probes']} probes of {fitted['n_models']} models "
            f"in {fitted['seconds']:.1f} s",
            file=sys.stderr,
        )


def _status(summary: RunSummary, status: str, engine: Engine | None) -> RunSummary:
    """``summary`` marked with the status of a run that did not finish (``refused``, ``interrupted``,
    ``failed``), with the seconds spent so far: only runs with status ``ok`` decide what is current."""
    summary.status = status
    if engine is not None:
        summary.seconds = {k: round(v, 3) for k, v in engine.seconds.items()}
    return summary

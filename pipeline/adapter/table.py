"""The query adapter in the store (table ``adapters``): fitted at the end of an onboarding run, found by a
query only when it was fitted on exactly what the query reads.

Provenance: the learned encoder's model key, the fingerprints of its view embeddings and of the probes, and
the sorted ids of the active meshes that have learned view embeddings. A run that ends with another
provenance, or another fit config, refits (seconds for a few hundred models, :mod:`pipeline.adapter.fit`);
one that changed nothing writes nothing. A run that stops early leaves the old row, which no longer
matches the store's models: queries then rank without an adapter (and say so) until a run finishes.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from pipeline import schemas
from pipeline.fingerprint import fingerprint
from pipeline.store import Store, slug, utcnow

#: a library past this many models is not fitted (the fit holds every view vector in memory, as the query
#: does; docs/results.md, section 11)
MAX_MODELS = 200_000


@dataclass
class Adapter:
    """A fitted adapter as a query uses it."""

    matrix: np.ndarray  # (dim, dim) float32
    provenance: str
    run_id: str
    n_models: int
    n_probes: int
    fit_json: str = "{}"  # the FitConfig it was fitted with


def provenance(encoder_id: str, view_fp: str, probe_fp: str, mesh_ids) -> str:
    """The fingerprint of what an adapter is fitted on (``mesh_ids``: the models with learned views)."""
    ids = sorted(str(m) for m in mesh_ids)
    return fingerprint({"encoder": encoder_id, "views": view_fp, "probes": probe_fp, "meshes": ids})


def _vectors(table: pa.Table) -> np.ndarray:
    col = table.column("embedding").combine_chunks()
    if len(col) == 0:
        return np.zeros((0, 0), np.float32)
    dim = col.type.list_size
    return np.asarray(col.flatten().to_numpy(zero_copy_only=False), np.float32).reshape(len(col), dim)


def _rows(con, store: Store, dataset: str, fp: str, sql: str = "query_view_embeddings") -> pa.Table:
    """``sql``'s rows over ``dataset`` at ``fp`` for the active meshes (``query_view_embeddings``: the query
    path's own statement, ``(mesh_idx, view_index, embedding)``; ``adapter_models``: the meshes only)."""
    from pipeline.db import load_sql

    d = store.dataset(dataset)
    if d is None:
        return pa.table(
            {
                "mesh_idx": pa.array([], pa.int32()),
                "mesh_id": pa.array([], pa.string()),
                "embedding": pa.array([], pa.list_(pa.float32(), 1)),
            }
        )
    con.register("query_view_source", d)
    try:
        return con.sql(load_sql(sql), params={"fingerprint": fp}).to_arrow_table()
    finally:
        con.unregister("query_view_source")


def _fit(P: pa.Table, V: pa.Table, present: np.ndarray, n_meshes: int, cfg) -> tuple[np.ndarray, int] | None:
    """The map fitted on the probes ``P`` of the models ``present`` (their ``mesh_idx``, of ``n_meshes``)
    against their learned views ``V``, and how many probes it saw; ``None`` when no probe is of those models."""
    from pipeline.adapter.fit import fit_adapter

    p_idx = np.asarray(P.column("mesh_idx").to_numpy(), np.int64)
    keep = np.isin(p_idx, present)
    if not keep.any():
        return None
    # models numbered by their position among those with views (the fit's model axis)
    number = np.full(n_meshes, -1, np.int64)
    number[present] = np.arange(len(present))
    v_idx = np.asarray(V.column("mesh_idx").to_numpy(), np.int64)
    matrix = fit_adapter(_vectors(P)[keep], number[p_idx[keep]], _vectors(V), number[v_idx], cfg)
    return matrix, int(keep.sum())


def latest_for(store: Store, encoder_id: str, wanted: str) -> dict | None:
    """The newest ``adapters`` row of ``encoder_id`` with provenance ``wanted`` (``None`` when none)."""
    if store.dataset("adapters") is None:
        return None
    t = store.read(
        "adapters", filter=(pc.field("encoder_id") == encoder_id) & (pc.field("provenance") == wanted)
    )
    if t.num_rows == 0:
        return None
    rows = t.to_pylist()
    return max(rows, key=lambda r: (r["created_at"], r["run_id"]))


def refresh(store: Store, spec, run_id: str, log=print) -> dict | None:
    """Fit and commit the store's adapter when its provenance or fit config changed (after an onboarding run
    that finished; ``spec``: the run's :class:`~pipeline.onboard.config.RunSpec`). Returns the new row's
    summary, or ``None`` when nothing was fitted (no probe step, nothing changed, too few models)."""
    from pipeline.db import connect, load_sql

    try:
        probe = spec.step("probe")
        views = spec.step("embed_image:learned_encoder")
    except StopIteration:
        return None
    encoder_id = probe.spec.key()
    store.refresh()
    con = connect(store, views=False)
    try:
        meshes = con.sql(load_sql("query_active_meshes")).to_arrow_table()
        if meshes.num_rows > MAX_MODELS:
            log(f"query adapter: {meshes.num_rows} models is past {MAX_MODELS}; not fitted")
            return None
        con.register("query_meshes", meshes.select(["mesh_idx", "mesh_id"]))
        models = _rows(con, store, views.dataset, views.fingerprint, "adapter_models")
        if models.num_rows < 2:
            return None
        wanted = provenance(
            encoder_id, views.fingerprint, probe.fingerprint, models.column("mesh_id").to_pylist()
        )
        fit_json = json.dumps(spec.cfg.adapter.describe(), sort_keys=True)
        old = latest_for(store, encoder_id, wanted)
        if old is not None and old["fit_json"] == fit_json:
            try:
                matrix_of(old)
                return None
            except ValueError as exc:  # a damaged row is refitted, not kept
                log(f"query adapter: {exc}; fitting it again")
        V = _rows(con, store, views.dataset, views.fingerprint)
        P = _rows(con, store, probe.dataset, probe.fingerprint)
    finally:
        con.close()
    present = np.asarray(models.column("mesh_idx").to_numpy(), np.int64)
    t0 = time.perf_counter()
    fitted = _fit(P, V, present, int(meshes.num_rows), spec.cfg.adapter)
    if fitted is None:
        return None
    matrix, n_probes = fitted
    seconds = time.perf_counter() - t0
    row = {
        "encoder_id": encoder_id,
        "provenance": wanted,
        "view_fingerprint": views.fingerprint,
        "probe_fingerprint": probe.fingerprint,
        "n_models": int(len(present)),
        "n_probes": n_probes,
        "dim": int(matrix.shape[0]),
        "matrix": matrix.astype("<f4").tobytes(),
        "fit_json": fit_json,
        "seconds": round(seconds, 3),
        "run_id": run_id,
        "created_at": utcnow(),
    }
    store.commit({"adapters": pa.Table.from_pylist([row], schema=schemas.ADAPTERS)}, run_id)
    return {k: row[k] for k in ("n_models", "n_probes", "seconds", "provenance")}


def matrix_of(row: dict) -> np.ndarray:
    """The (dim, dim) float32 matrix of an ``adapters`` row (a damaged row: ValueError)."""
    dim = int(row["dim"])
    m = np.frombuffer(row["matrix"], dtype="<f4")
    if m.size != dim * dim or not np.isfinite(m).all():
        raise ValueError(f"adapter row of run {row['run_id']} is damaged ({m.size} values for dim {dim})")
    return m.reshape(dim, dim).astype(np.float32)


def for_query(store: Store, encoder_id: str, view_fp: str, probe_fp: str | None, mesh_ids) -> Adapter | None:
    """The adapter fitted on exactly these models, encoder and probes (``None`` when the store has none)."""
    if not probe_fp:
        return None
    row = latest_for(store, encoder_id, provenance(encoder_id, view_fp, probe_fp, mesh_ids))
    if row is None:
        return None
    return Adapter(
        matrix_of(row),
        row["provenance"],
        row["run_id"],
        row["n_models"],
        row["n_probes"],
        row["fit_json"] or "{}",
    )


def refit_for(tables, adapter: Adapter) -> Adapter | None:
    """The adapter a store holding only ``tables``' meshes would have: fitted as ``adapter`` was, on the
    probes and learned views of those meshes (the open-set split, :mod:`pipeline.evaluate.openset_split`,
    which takes meshes out of a store's tables). ``None`` when fewer than two models, or no probe of them, are left."""
    from pipeline.adapter.fit import FitConfig
    from pipeline.db import connect

    fps = tables.onboarding.fingerprints
    key = tables.onboarding.models["learned_encoder"]
    con = connect(tables.store, views=False)
    try:
        con.register("query_meshes", tables.meshes.select(["mesh_idx", "mesh_id"]))
        P = _rows(con, tables.store, probe_dataset(key), fps["probe"])
    finally:
        con.close()
    V = tables.learned_views
    present = np.unique(np.asarray(V.column("mesh_idx").to_numpy(), np.int64))
    if len(present) < 2:
        return None
    cfg = FitConfig(
        **{k: tuple(v) if isinstance(v, list) else v for k, v in json.loads(adapter.fit_json).items()}
    )
    fitted = _fit(P, V, present, tables.meshes.num_rows, cfg)
    if fitted is None:
        return None
    matrix, n_probes = fitted
    ids = tables.meshes.column("mesh_id").to_pylist()
    wanted = provenance(key, fps["embed_image:learned_encoder"], fps["probe"], [ids[i] for i in present])
    return Adapter(matrix, wanted, adapter.run_id, int(len(present)), n_probes, adapter.fit_json)


def probe_dataset(encoder_id: str) -> str:
    return f"probe_embeddings/{slug(encoder_id)}"

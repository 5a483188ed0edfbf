"""Stage-1 SQL cost of the fallback unit: captions vs meshes (and, optionally, an older SQL file).

    python bench/bench_fallback_unit.py --rows 200000 [--old-sql OLD.sql] [--repeats 7]

Synthetic unit vectors (512-d, 8 captions per model) in the product's sliced layout, one DuckDB thread,
interleaved runs; prints median wall ms per SQL and case and the ratios to the first column. Cases: tau
between the 50th and 51st best model (50 pass: the fallback does not fire) and tau = 2 (it fires, k = 10).
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import pyarrow as pa


def main() -> None:
    import duckdb

    from pipeline.db import load_sql
    from pipeline.query.stage1 import query_params, slice_layout

    ap = argparse.ArgumentParser()
    ap.add_argument("--rows", type=int, default=200_000)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--old-sql", help="an older stage1_text_filter.sql (without $fallback_unit) to compare")
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    n, dim = args.rows - args.rows % 8, 512
    x = rng.standard_normal((n, dim)).astype(np.float32)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    mesh = np.repeat(np.arange(n // 8), 8).astype(np.int32)
    emb = pa.FixedSizeListArray.from_arrays(pa.array(x.reshape(-1)), dim)
    con = duckdb.connect()
    con.execute("SET threads = 1")
    con.register("stage1_captions", slice_layout(pa.table({"mesh_idx": mesh, "embedding": emb})))
    q = rng.standard_normal(dim).astype(np.float32)
    q /= np.linalg.norm(q)
    best = np.sort((x @ q).reshape(-1, 8).max(axis=1))[::-1]
    sqls = {
        "captions": (load_sql("stage1_text_filter"), "captions"),
        "meshes": (load_sql("stage1_text_filter"), "meshes"),
    }
    if args.old_sql:
        sqls = {"old": (open(args.old_sql).read(), None), **sqls}
    base = query_params(q, dim // 8)
    for case, tau in (("50 pass", float((best[49] + best[50]) / 2)), ("fallback (tau 2)", 2.0)):
        times: dict[str, list[float]] = {k: [] for k in sqls}
        for _ in range(args.repeats):
            for name, (sql, unit) in sqls.items():
                params = {**base, "threshold": tau, "fallback_k": 10}
                if unit:
                    params["fallback_unit"] = unit
                t0 = time.perf_counter()
                con.execute(sql, params).fetchnumpy()
                times[name].append(time.perf_counter() - t0)
        med = {k: 1000 * statistics.median(v) for k, v in times.items()}
        first = next(iter(med.values()))
        print(case + ": " + ", ".join(f"{k} {v:.1f} ms ({v / first:.2f}x)" for k, v in med.items()))


if __name__ == "__main__":
    main()

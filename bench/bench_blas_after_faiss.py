"""A NumPy matrix-vector product right after a faiss search, against the alternatives, one process.

    OMP_NUM_THREADS=2 python bench/bench_blas_after_faiss.py

faiss's OpenMP threads keep spinning for a while after a search; a BLAS product started then waits on
them. The stage-1 index scores its delta rows and the survivors' rows right after its range search, so
it uses ``pipeline.index.snapshot.row_scores`` (an einsum loop, no BLAS). Prints the median of 20 of
each, every one timed right after a small IVF range search, and the BLAS product on an idle process.
"""

from __future__ import annotations

import sys
import time

import numpy as np


def main() -> int:
    import faiss

    rng = np.random.default_rng(0)
    x = rng.standard_normal((200_000, 384)).astype(np.float32)
    index = faiss.index_factory(384, "IVF400,SQ4", faiss.METRIC_INNER_PRODUCT)
    index.train(x[:40_000])
    index.add(x)
    faiss.extract_index_ivf(index).parallel_mode = 1
    index.nprobe = 40
    rows = rng.standard_normal((8008, 384)).astype(np.float32)  # the 10M benchmark's delta after its commits
    q = x[0]

    def after_search(f) -> float:
        times = []
        for _ in range(20):
            index.range_search(q[None], 5.0)
            t0 = time.perf_counter()
            f()
            times.append(time.perf_counter() - t0)
        return float(np.median(times) * 1e3)

    flat = faiss.IndexFlatIP(384)
    flat.add(rows)
    print("| 8,008 x 384 rows times a query | median ms |")
    print("|---|---|")
    print(f"| NumPy `rows @ q` (BLAS) after a faiss search | {after_search(lambda: rows @ q):.2f} |")
    print(
        f"| `np.einsum('ij,j->i')` after a faiss search | {after_search(lambda: np.einsum('ij,j->i', rows, q)):.2f} |"
    )
    print(
        f"| faiss `IndexFlatIP.search` after a faiss search | {after_search(lambda: flat.search(q[None], 10)):.2f} |"
    )
    idle = []
    for _ in range(20):
        t0 = time.perf_counter()
        rows @ q
        idle.append(time.perf_counter() - t0)
    print(f"| NumPy `rows @ q`, no faiss search before | {np.median(idle) * 1e3:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

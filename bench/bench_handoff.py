"""What the pose-estimator hand-off costs an answer: the first fill (reads the views' cameras) and warm fills.

    python bench/bench_handoff.py --store STORE [--repeat 50] [--top 5]

Opens a Retriever without models and fills the hand-off fields (units, size, best-view pose, K) of
``--top`` candidates: once cold (a library of up to 2,000 meshes has every view camera read in one scan),
then ``--repeat`` times warm, and prints the medians. Results: docs/query.md ("Hand-off to a pose estimator").
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
    p.add_argument("--store", required=True)
    p.add_argument("--repeat", type=int, default=50)
    p.add_argument("--top", type=int, default=5)
    args = p.parse_args()
    from pipeline.query import Retriever
    from pipeline.query.results import Candidate

    with Retriever.open(args.store, profile="auto", preload=False) as r:
        ids = r.mesh_ids[: args.top]
        cands = [Candidate(i + 1, m, "", "", None, 0.5, 0) for i, m in enumerate(ids)]
        t0 = time.perf_counter()
        r.handoff.fill(cands)
        cold = (time.perf_counter() - t0) * 1000
        warm = []
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            r.handoff.fill(cands)
            warm.append((time.perf_counter() - t0) * 1000)
        assert all(c.best_view_pose is not None for c in cands), "views without cameras in this store"
        print("| meshes | candidates | first fill (ms) | warm fill, median (ms) |")
        print("|---|---|---|---|")
        print(f"| {r.n_meshes} | {len(cands)} | {cold:.1f} | {statistics.median(warm):.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

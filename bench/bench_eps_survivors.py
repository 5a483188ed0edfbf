"""Survivors of the stage-1 range search at ``tau - eps`` for several error bounds ``eps``, on an index and
the queries that ``bench/bench_stage1_index.py`` left in its work folder.

    python bench/bench_eps_survivors.py --workdir /work/bench10m --rows 10000000 --eps 0.0445,0.1,0.16

Every row the range search returns is a caption whose model is rescored exactly from the float file, so
the survivors are what a larger codec error costs after the scan. The radius is widened on the index as
built: that stands in for a codec whose error bound is eps, whose range search at ``tau - eps`` must
return every row with an estimate above that radius (about as many rows as this search returns).
Prints, per eps, the survivors per tau query (median, 90th percentile,
largest) and the median range-search time.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from stage1_workdir import add_arguments, open_workdir  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(p, queries=24)
    p.add_argument("--eps", default="0.0445,0.1,0.16", help="comma-separated error bounds")
    a = p.parse_args(argv)
    import faiss

    w = open_workdir(a)
    man, index, q, taus, sel = w.manifest, w.index, w.queries, w.taus, w.tau_queries
    index.nprobe = int(man["nprobe"])
    faiss.extract_index_ivf(index).parallel_mode = 1
    print(f"index: {man['codec']}, nlist {man['nlist']}, nprobe {man['nprobe']}, built eps {man['eps']:.4f}")
    print("| eps | survivors: median | 90th percentile | largest | range search p50 |")
    print("|---|---|---|---|---|")
    for eps in (float(v) for v in a.eps.split(",")):
        surv, ms = [], []
        for i in sel:
            t0 = time.perf_counter()
            _, _, labels = index.range_search(q[i : i + 1], float(taus[i] - eps))
            ms.append((time.perf_counter() - t0) * 1000)
            surv.append(len(labels))
        print(
            f"| {eps:g} | {np.median(surv):,.0f} | {np.percentile(surv, 90):,.0f} | {max(surv):,} "
            f"| {np.median(ms):.0f} ms |",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())

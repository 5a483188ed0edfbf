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
import json
import sys
import time
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--workdir", type=Path, required=True, help="bench_stage1_index.py's --workdir")
    p.add_argument("--rows", type=int, required=True)
    p.add_argument("--dim", type=int, default=384)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--eps", default="0.0445,0.1,0.16", help="comma-separated error bounds")
    p.add_argument("--queries", type=int, default=24, help="tau queries used (the first ones)")
    p.add_argument("--threads", type=int, default=2)
    a = p.parse_args(argv)
    import faiss

    faiss.omp_set_num_threads(a.threads)
    root = a.workdir / f"store-{a.rows}-{a.dim}-{a.seed}" / "_index" / "stage1"
    dirs = sorted(root.glob("*/manifest.json"))
    if not dirs:
        print(
            f"error: no stage-1 index under {root} (run bench/bench_stage1_index.py first)", file=sys.stderr
        )
        return 1
    man = json.loads(dirs[0].read_text())
    index = faiss.read_index(str(dirs[0].parent / man["base"]["faiss"]))
    index.nprobe = int(man["nprobe"])
    faiss.extract_index_ivf(index).parallel_mode = 1
    z = np.load(a.workdir / f"queries-{a.rows}.npz")
    q, taus = z["queries"], z["taus"]
    sel = [i for i in range(len(q)) if np.isfinite(taus[i])][: a.queries]
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

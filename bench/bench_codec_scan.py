"""Scan cost, error and range-search recall of faiss IVF codecs for stage 1, one thread, on the stage-1
benchmark's vectors.

    python bench/bench_codec_scan.py --rows 500000 --codecs SQ4,SQ8,RaBitQ,RaBitQ4,RaBitQfs,RaBitQfs4,PQ96x4fs,PQ192x4fs

Per codec: the codes a query scans (its probed lists, against nprobe lists of the mean size), nanoseconds
per scanned code for a k-NN search (k = 2000), the codec's error bound ``eps`` (1.2 x the largest error of
its own k-NN inner-product estimates against the exact products), and a range search at ``r - eps`` for
two radii per query: ``tight``, the exact score of the ``--tight``-th best probed row (about what a stage-1
tau lets through at 10M rows: the 10M benchmark's queries keep a median of 518 survivors), and ``loose``,
the ``--loose``-th. For each: ns per scanned code, survivors per query (median), and the range recall, the
share of probed rows with exact score >= r that the range search returned. A codec is usable only where
that recall is 1: the product relies on the range search returning every row within ``eps`` of tau.
Last column: the share of the probed rows a range search at radius -1.5 returns; every unit-vector row
scores above it, so anything below 1 is rows lost at a low radius.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_stage1_index import BATCH_MESHES, PER_MESH, caption_batch, make_queries, topics  # noqa: E402


def range_stats(index, x, q, assign, lists, rank: int, eps: float):
    """(ns per scanned code, median survivors, mean and min range recall) at radius rank-th best - eps."""
    ns, survivors, recall = [], [], []
    for i in range(len(q)):
        probed = np.flatnonzero(np.isin(assign, lists[i]))
        exact = x[probed] @ q[i]
        r = float(np.sort(exact)[-min(rank, len(exact))])
        t0 = time.perf_counter()
        _, _, ids = index.range_search(q[i : i + 1], r - eps)
        ns.append((time.perf_counter() - t0) * 1e9 / len(probed))
        survivors.append(len(ids))
        recall.append(float(np.isin(probed[exact >= r], ids).mean()))
    return float(np.median(ns)), float(np.median(survivors)), float(np.mean(recall)), float(np.min(recall))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rows", type=int, default=500_000)
    p.add_argument("--dim", type=int, default=384)
    p.add_argument("--nlist", type=int, default=1000)
    p.add_argument("--nprobe", type=int, default=30)
    p.add_argument("--queries", type=int, default=30)
    p.add_argument("--tight", type=int, default=500, help="rank of the tight radius among probed rows")
    p.add_argument("--loose", type=int, default=5000, help="rank of the loose radius among probed rows")
    p.add_argument("--codecs", default="SQ4,SQ8,RaBitQ,RaBitQ4,RaBitQfs,RaBitQfs4,PQ96x4fs,PQ192x4fs")
    a = p.parse_args(argv)
    import faiss

    faiss.omp_set_num_threads(1)
    n_mesh = a.rows // PER_MESH
    common, tops = topics(n_mesh, a.dim, 0)
    x = np.concatenate(
        [
            caption_batch(m0, min(n_mesh, m0 + BATCH_MESHES), a.dim, 0, common, tops)
            for m0 in range(0, n_mesh, BATCH_MESHES)
        ]
    )
    q = make_queries(len(x), a.dim, 0, a.queries)
    print(
        "| codec | bytes/code | codes scanned per query (median) / at mean list size | k-NN ns/code | eps "
        f"| tight ({a.tight}): ns/code, survivors, range recall (min) "
        f"| loose ({a.loose}): ns/code, survivors, range recall (min) | radius -1.5: rows returned |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for spec in a.codecs.split(","):
        index = faiss.index_factory(a.dim, f"IVF{a.nlist},{spec}", faiss.METRIC_INNER_PRODUCT)
        index.train(x[: min(len(x), 100 * a.nlist)])
        index.add(x)
        ivf = faiss.extract_index_ivf(index)
        index.nprobe = a.nprobe
        sizes = np.array([ivf.invlists.list_size(j) for j in range(ivf.nlist)])
        _, lists = ivf.quantizer.search(q, a.nprobe)
        assign = ivf.quantizer.search(x, 1)[1][:, 0]
        scanned = float(np.median(sizes[lists].sum(1)))
        knn, err = [], 0.0
        for i in range(len(q)):
            t0 = time.perf_counter()
            d, ids = index.search(q[i : i + 1], 2000)
            knn.append(time.perf_counter() - t0)
            ok = ids[0] >= 0
            err = max(err, float(np.abs(d[0][ok] - x[ids[0][ok]] @ q[i]).max()))
        eps = 1.2 * err
        cells = []
        for rank in (a.tight, a.loose):
            t, s, rec, rec_min = range_stats(index, x, q, assign, lists, rank, eps)
            cells.append(f"{t:.0f}, {s:.0f}, {rec:.3f} ({rec_min:.3f})")
        low = [
            len(index.range_search(q[i : i + 1], -1.5)[2]) / np.isin(assign, lists[i]).sum() for i in range(len(q))
        ]
        print(
            f"| {spec} | {ivf.code_size} | {scanned:.0f} / {a.nprobe * sizes.mean():.0f} | "
            f"{np.median(knn) * 1e9 / scanned:.0f} | {eps:.4f} | {cells[0]} | {cells[1]} | {np.mean(low):.3f} |",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Scan cost and error of faiss IVF codecs for stage 1, one thread, on the stage-1 benchmark's vectors.

    python bench/bench_codec_scan.py --rows 500000 --codecs SQ4,SQ8,SQfp16,RaBitQ,RaBitQfs,RaBitQ4,PQ96x4fs

Per codec: the codes a query scans (its probed lists; against nprobe lists of the mean size), nanoseconds
per scanned code for a k-NN search (k = 2000) and for a range search, and the
largest error of the codec's own inner-product estimate (the distances its k-NN search returns against
the exact products of the rows it returned). The range search at ``tau - eps`` lets through every row
within that error of tau, so a codec is only as useful as its speed at an error bound small enough to
keep the survivors few (docs/performance.md, "10M rows").
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_stage1_index import BATCH_MESHES, PER_MESH, caption_batch, make_queries, topics  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rows", type=int, default=500_000)
    p.add_argument("--dim", type=int, default=384)
    p.add_argument("--nlist", type=int, default=1000)
    p.add_argument("--nprobe", type=int, default=30)
    p.add_argument("--queries", type=int, default=30)
    p.add_argument("--codecs", default="SQ4,SQ8,SQfp16,RaBitQ,RaBitQfs,RaBitQ4,PQ96x4fs")
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
    print("| codec | bytes/code | codes scanned per query (median) / at mean list size | k-NN ns/code | range ns/code | largest estimate error |")
    print("|---|---|---|---|---|---|")
    for spec in a.codecs.split(","):
        index = faiss.index_factory(a.dim, f"IVF{a.nlist},{spec}", faiss.METRIC_INNER_PRODUCT)
        index.train(x[: min(len(x), 100 * a.nlist)])
        index.add(x)
        ivf = faiss.extract_index_ivf(index)
        index.nprobe = a.nprobe
        sizes = np.array([ivf.invlists.list_size(j) for j in range(ivf.nlist)])
        _, lists = ivf.quantizer.search(q, a.nprobe)
        scanned = float(np.median(sizes[lists].sum(1)))
        knn, rng_t, err = [], [], 0.0
        for i in range(len(q)):
            t0 = time.perf_counter()
            d, ids = index.search(q[i : i + 1], 2000)
            knn.append(time.perf_counter() - t0)
            ok = ids[0] >= 0
            err = max(err, float(np.abs(d[0][ok] - x[ids[0][ok]] @ q[i]).max()))
            t0 = time.perf_counter()
            index.range_search(q[i : i + 1], 0.7)
            rng_t.append(time.perf_counter() - t0)
        print(
            f"| {spec} | {ivf.code_size} | {scanned:.0f} / {a.nprobe * sizes.mean():.0f} | "
            f"{np.median(knn) * 1e9 / scanned:.0f} | "
            f"{np.median(rng_t) * 1e9 / scanned:.0f} | {err:.4f} |",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())

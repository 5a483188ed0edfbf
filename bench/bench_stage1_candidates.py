"""Which faiss IVF codec for the stage-1 index: SQ8, SQ4 or RaBitQ, at several nprobe (in memory).

    python bench/bench_stage1_candidates.py 1000000 sq8,sq4,rabitq 0.02

Synthetic clustered caption embeddings (384-d, 8 per model, the same generator shape as
``bench/bench_stage1_index.py``), 40 queries, each with a tau that lets 1..100 models pass. Per codec and
nprobe: the range search at tau - eps (eps the third argument), exact rescoring of every caption of each
surviving model, and the tau-set recall against the exact per-model scores. Build time and code bytes per
row are printed too. Results: docs/performance.md, "Stage-1 index".
"""

from __future__ import annotations

import sys
import time

import numpy as np


def data(n: int, d: int, per: int, rng) -> np.ndarray:
    nm = n // per
    nt = max(16, nm // 64)
    common = rng.standard_normal(d).astype(np.float32)
    common /= np.linalg.norm(common)
    topics = rng.standard_normal((nt, d)).astype(np.float32) / np.sqrt(d)
    mt = rng.integers(nt, size=nm)
    x = np.empty((n, d), np.float32)
    for i in range(0, nm, 16384):
        j = min(nm, i + 16384)
        cen = (
            0.8 * common
            + topics[mt[i:j]]
            + 0.6 * rng.standard_normal((j - i, d)).astype(np.float32) / np.sqrt(d)
        )
        cap = np.repeat(cen, per, axis=0) + 0.5 * rng.standard_normal(((j - i) * per, d)).astype(
            np.float32
        ) / np.sqrt(d)
        x[i * per : j * per] = cap / np.linalg.norm(cap, axis=1, keepdims=True)
    return x


def main() -> int:
    import faiss

    faiss.omp_set_num_threads(2)
    n, d, per, nq = int(sys.argv[1]), 384, 8, 40
    codecs = sys.argv[2].split(",") if len(sys.argv) > 2 else ["sq8", "sq4", "rabitq"]
    eps = float(sys.argv[3]) if len(sys.argv) > 3 else 0.02
    rng = np.random.default_rng(0)
    x = data(n, d, per, rng)
    nm = n // per
    mesh = np.arange(n) // per
    qs = x[rng.integers(n, size=nq)] + 0.5 * rng.standard_normal((nq, d)).astype(np.float32) / np.sqrt(d)
    qs = (qs / np.linalg.norm(qs, axis=1, keepdims=True)).astype(np.float32)
    t0 = time.perf_counter()
    s = x @ qs[0]
    print(f"numpy single query {1000 * (time.perf_counter() - t0):.1f} ms")
    ms = (x @ qs.T).reshape(nm, per, nq).max(1)
    taus, sets = [], []
    for t in range(nq):
        srt = np.sort(ms[:, t])[::-1]
        k = int(rng.integers(1, 100))
        taus.append((srt[k - 1] + srt[k]) / 2)
        sets.append(set(np.flatnonzero(ms[:, t] >= taus[-1]).tolist()))
    del s
    nl = int(4 * np.sqrt(n))
    for c in codecs:
        qz = faiss.IndexFlatIP(d)
        if c == "sq8":
            ix = faiss.IndexIVFScalarQuantizer(
                qz, d, nl, faiss.ScalarQuantizer.QT_8bit, faiss.METRIC_INNER_PRODUCT
            )
        elif c == "sq4":
            ix = faiss.IndexIVFScalarQuantizer(
                qz, d, nl, faiss.ScalarQuantizer.QT_4bit, faiss.METRIC_INNER_PRODUCT
            )
        else:
            ix = faiss.IndexIVFRaBitQ(qz, d, nl, faiss.METRIC_INNER_PRODUCT)
        t0 = time.perf_counter()
        ix.train(x[rng.choice(n, min(n, 200000), replace=False)])
        ix.add(x)
        build = time.perf_counter() - t0
        for nprobe in (8, 16, 32, 64):
            ix.nprobe = nprobe
            rec, tm = [], []
            for t in range(nq):
                q = qs[t : t + 1]
                t1 = time.perf_counter()
                _, _, ids = ix.range_search(q, float(taus[t] - eps))
                m = np.unique(mesh[ids])
                rows = (m[:, None] * per + np.arange(per)).ravel()
                sc = (x[rows] @ q[0]).reshape(-1, per).max(1)
                got = set(m[sc >= taus[t]].tolist())
                tm.append((time.perf_counter() - t1) * 1000)
                rec.append(len(got & sets[t]) / len(sets[t]))
            print(
                f"{c:7s} nlist {nl} nprobe {nprobe:3d}  build {build:6.1f}s  p50 {np.median(tm):6.2f} ms  "
                f"tau recall {np.mean(rec):.4f} (min {np.min(rec):.3f})  code {ix.sa_code_size()} B/row"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())

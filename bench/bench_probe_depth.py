"""How deep a tau query must search: for each tau query that ``bench/bench_stage1_index.py`` left in its
work folder, where its tau-set models' captions lie among the index's lists.

    python bench/bench_probe_depth.py --workdir /work/bench10m --rows 10000000 --queries 40

Per query: one range search at ``tau - eps`` over every list, the exact scores of the rows it returns, and
for each tau-set model (exact max >= tau) the best-ranked list (lists ordered by their centroid's score
against the query) that holds one of its surviving captions. Prints per query the tau, the tau-set size,
the deepest such list rank (0: the best list) and how far below tau that list's centroid scores
(``delta needed``); then the counts that ``docs/performance.md`` ("The probe depth follows tau") quotes.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from stage1_workdir import add_arguments, open_workdir  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(p, queries=40)
    a = p.parse_args(argv)
    import faiss

    from pipeline.index.layout import base_array

    w = open_workdir(a)
    d, man, index, q, taus, sel = w.directory, w.manifest, w.index, w.queries, w.taus, w.tau_queries
    ivf = faiss.extract_index_ivf(index)
    index.nprobe = ivf.nlist
    vecs = np.memmap(d / man["vectors"], np.float32, "r", shape=(man["n_slots"], man["dim"]))
    mesh, centroids = base_array(d, man, "mesh_code"), base_array(d, man, "centroids")
    print(f"index: {man['codec']}, nlist {ivf.nlist}, eps {man['eps']:.4f}; {len(sel)} tau queries")
    print("| query | tau | tau-set models | deepest list rank needed | delta needed |")
    print("|---|---|---|---|---|")
    rows = []
    for i in sel:
        tau = float(taus[i])
        _, _, labels = index.range_search(q[i : i + 1], tau - man["eps"])
        labels = np.sort(labels)
        keep = labels[np.asarray(vecs[labels] @ q[i]) >= tau]
        cs = centroids @ q[i]
        rank = np.empty(len(cs), np.int64)
        rank[np.argsort(-cs)] = np.arange(len(cs))
        lists = ivf.quantizer.search(np.ascontiguousarray(vecs[keep]), 1)[1][:, 0]
        best: dict[int, int] = {}
        for m, lst in zip(mesh[keep].tolist(), lists.tolist(), strict=True):
            if m not in best or rank[lst] < rank[best[m]]:
                best[m] = lst
        depth = max(int(rank[lst]) for lst in best.values())
        need = tau - min(float(cs[lst]) for lst in best.values())
        rows.append((tau, len(best), depth, need))
        print(f"| {i} | {tau:.3f} | {len(best)} | {depth} | {need:+.3f} |", flush=True)
    tau = np.array([r[0] for r in rows])
    depth = np.array([r[2] for r in rows])
    need = np.array([r[3] for r in rows])
    deep = depth > 10
    print(f"\nevery tau-set model in the best list: {int((depth == 0).sum())} of {len(rows)} queries")
    print(f"largest delta needed: {need.max():.3f}")
    if deep.any():
        print(
            f"deeper than 10 lists: {int(deep.sum())} queries, {depth[deep].min()}-{depth[deep].max()} lists, "
            f"tau {tau[deep].min():.2f}-{tau[deep].max():.2f}, largest delta needed {need[deep].max():.3f}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The ``paper`` metric set: the reference scripts' definitions, which are what the paper's numbers mean.

From the authors' ``object_retrieval/i2i_seg_dino.py`` (mAP@k, YCB-V and HOPE tables) and
``object_retrieval/retrieval_mi3dor_eval.py`` (the MI3DOR set), as written out in ``docs/evaluation.md``:

* **mAP@k** ranks library *views*: every reference view is an item carrying its mesh's label, sorted by
  score. Walk the top k items; at each relevant one record precision = hits so far / rank; AP@k = mean of
  the recorded precisions (the *hits* normaliser; 0 when none). So mAP@k can fall as k grows.
* **MI3DOR set** over one ranking of reference items (here: the ranked meshes), ``rel_i`` = item i has the
  query's label, ``kappa`` = relevant items *in the ranking*, ``N`` = its length; a query with kappa = 0 is
  not counted. NN = rel_1; FT = hits in the top kappa / kappa; ST = hits in the top min(2 kappa, N) /
  kappa; F = F1 of precision and recall over the top min(20, N); nDCG over the top K = min(2 kappa, N)
  with gain rel_i / log2(i + 1), ideal = min(kappa, K) ones; AP over the whole ranking; NMRR = (AVR -
  (kappa + 1) / 2) / (K - (kappa + 1) / 2) with AVR the mean over kappa of the relevant items' ranks
  within the top K (K + 1 for each one not there), 0 when that denominator is <= 0.

Every function takes a relevance vector over the ranking (ties already ordered, see
:func:`pipeline.evaluate.metrics.relevance_vector`).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

MAP_KS = (1, 3, 5, 10)
F_AT = 20
#: Keys of the MI3DOR part (``None`` for a query with no relevant item in its ranking).
MI3DOR_KEYS = ("NN", "FT", "ST", "F", "nDCG", "AP", "NMRR")


def view_ap_at_k(rel_views: Sequence[bool], k: int) -> float:
    """AP@k over the view ranking with the hits normaliser: mean precision at the relevant items in the top k."""
    rel = np.asarray(rel_views[:k], dtype=bool)
    ranks = np.flatnonzero(rel) + 1
    if not len(ranks):
        return 0.0
    return float(np.mean(np.arange(1, len(ranks) + 1) / ranks))


def mi3dor(rel_items: Sequence[bool]) -> dict[str, float] | None:
    """NN, FT, ST, F, nDCG, AP and NMRR of one ranking; ``None`` when it holds no relevant item (kappa = 0)."""
    rel = np.asarray(rel_items, dtype=bool)
    n = len(rel)
    kappa = int(rel.sum())
    if kappa == 0:
        return None
    cum = np.cumsum(rel)
    k2 = min(2 * kappa, n)
    m = min(F_AT, n)
    hits_f = int(cum[m - 1])
    p, r = hits_f / m, hits_f / kappa
    f = 2 * p * r / (p + r) if hits_f else 0.0
    disc = 1.0 / np.log2(np.arange(2, k2 + 2))  # 1 / log2(i + 1), i = 1..K
    ndcg = float((rel[:k2] * disc).sum() / disc[: min(kappa, k2)].sum())
    ranks = np.flatnonzero(rel) + 1
    ap = float(np.mean(np.arange(1, kappa + 1) / ranks))
    within = ranks[ranks <= k2]
    avr = (within.sum() + (kappa - len(within)) * (k2 + 1)) / kappa
    denom = k2 - (kappa + 1) / 2
    nmrr = float((avr - (kappa + 1) / 2) / denom) if denom > 0 else 0.0
    return {
        "NN": float(rel[0]),
        "FT": int(cum[kappa - 1]) / kappa,
        "ST": int(cum[k2 - 1]) / kappa,
        "F": float(f),
        "nDCG": ndcg,
        "AP": ap,
        "NMRR": nmrr,
    }


def query_metrics(
    rel_views: Sequence[bool], rel_items: Sequence[bool], map_ks: Iterable[int] = MAP_KS
) -> dict[str, float | None]:
    """The paper set for one query: view-level mAP@k plus the MI3DOR measures over the item ranking."""
    out: dict[str, float | None] = {f"mAP@{k}": view_ap_at_k(rel_views, k) for k in map_ks}
    mi = mi3dor(rel_items)
    out.update(mi if mi is not None else dict.fromkeys(MI3DOR_KEYS))
    return out


def aggregate(per_query: Sequence[dict]) -> dict[str, float]:
    """Means over the counted queries; NN as a percentage (as the reference reports it); NMRR -> ANMRR.

    ``n`` is the number of queries (mAP@k counts every one), ``n_mi3dor`` those with a relevant item in
    their ranking (the MI3DOR measures' denominator).
    """
    if not per_query:
        return {"n": 0, "n_mi3dor": 0}
    out: dict[str, float] = {}
    for key in per_query[0]:
        vals = [q[key] for q in per_query if q.get(key) is not None]
        name = "ANMRR" if key == "NMRR" else key
        out[name] = float(np.mean(vals)) if vals else float("nan")
        if key == "NN" and vals:
            out[name] *= 100.0
    out["n"] = len(per_query)
    out["n_mi3dor"] = sum(q.get("NN") is not None for q in per_query)
    return out


HEADLINE = ("mAP@1", "mAP@3", "mAP@5", "mAP@10", "NN", "FT", "ST", "F", "nDCG", "AP", "ANMRR")

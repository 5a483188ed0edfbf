"""Retrieval metrics, in two sets (``--metrics``):

* ``paper`` (default): the reference scripts' definitions, which are what the paper's numbers mean: mAP@k
  over library *views* with the hits normaliser, and the MI3DOR measures as the reference computes them
  (:mod:`pipeline.evaluate.metrics_paper`).
* ``standard``: the textbook definitions in this module: mAP@k over the ranked meshes normalised by
  min(k, R), top-k accuracy, and NN, FT, ST, F, DCG, MPEG-7 ANMRR with kappa = relevant items in the library.

Every function here scores ONE query from its relevance vector ``rel`` (``rel[i]`` is true when the item the
system returned at rank ``i + 1`` is relevant) and ``n_relevant``, the number of relevant items in the whole
library. The returned list may be shorter than the library (two-stage retrieval only ranks the stage-1
candidates): relevant items that were not returned simply never count as found. Formulas are written out
in ``docs/evaluation.md``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np

METRIC_SETS = ("paper", "standard")
MAP_KS = (1, 3, 5, 10)
TOP_KS = (1, 5)
F_AT = 20  # MI3DOR reference: F-measure over the top 20
MAP_NORMALISERS = ("min", "relevant", "hits")
TIE_POLICIES = ("pessimistic", "optimistic", "list")


def relevance_vector(
    ranked_ids: Sequence[str],
    relevant: set[str],
    scores: Sequence[float] | None = None,
    ties: str = "pessimistic",
) -> np.ndarray:
    """Relevance of each returned item, with runs of equal ``scores`` ordered by the tie policy.

    ``scores`` are the keys the ranking was sorted by (floats, or tuples such as (image, text) scores).

    ``pessimistic`` puts the non-relevant items of a tied run first (a constant-score system earns nothing),
    ``optimistic`` the relevant ones, ``list`` keeps the order the system returned.
    """
    if ties not in TIE_POLICIES:
        raise ValueError(f"unknown tie policy {ties!r}; choose from {', '.join(TIE_POLICIES)}")
    if isinstance(ranked_ids, np.ndarray):
        rel = np.isin(ranked_ids, list(relevant)) if relevant else np.zeros(len(ranked_ids), bool)
    else:
        rel = np.array([i in relevant for i in ranked_ids], dtype=bool)
    if scores is None or ties == "list" or len(rel) < 2:
        return rel
    # floats or tuples of floats (a sort key), one row per item; NaN never equals anything
    keys = np.asarray(scores if isinstance(scores, np.ndarray) else list(scores), dtype=np.float64)
    keys = keys.reshape(len(rel), -1)
    new_run = np.ones(len(rel), bool)
    new_run[1:] = np.any(keys[1:] != keys[:-1], axis=1)
    starts = np.flatnonzero(new_run)
    run = np.cumsum(new_run) - 1
    length = np.diff(np.append(starts, len(rel)))[run]
    hits = np.add.reduceat(rel.astype(np.int64), starts)[run]
    pos = np.arange(len(rel)) - starts[run]
    if ties == "pessimistic":
        return pos >= length - hits
    return pos < hits


def _hits(rel: np.ndarray, k: int) -> int:
    return int(np.asarray(rel[:k], dtype=bool).sum())


def average_precision_at_k(rel: Sequence[bool], n_relevant: int, k: int, normaliser: str = "min") -> float:
    """AP@k = (1 / Z) * sum_{i<=k} P(i) * rel(i), with Z = min(k, R) by default.

    ``normaliser``: ``min`` (Z = min(k, R), so a perfect ranking scores 1 at every k), ``relevant``
    (Z = R) or ``hits`` (Z = relevant items found in the top k; 0 when none).
    """
    if normaliser not in MAP_NORMALISERS:
        raise ValueError(f"unknown mAP normaliser {normaliser!r}; choose from {', '.join(MAP_NORMALISERS)}")
    rel = np.asarray(rel[:k], dtype=bool)
    if n_relevant <= 0 or not rel.any():
        return 0.0
    ranks = np.flatnonzero(rel) + 1
    precisions = np.arange(1, len(ranks) + 1) / ranks
    z = {"min": min(k, n_relevant), "relevant": n_relevant, "hits": len(ranks)}[normaliser]
    return float(precisions.sum() / z)


def average_precision(rel: Sequence[bool], n_relevant: int) -> float:
    """Uncut AP: mean over all R relevant items of the precision at its rank (0 for unreturned ones)."""
    return average_precision_at_k(rel, n_relevant, max(len(rel), 1), normaliser="relevant")


def top_k_hit(rel: Sequence[bool], k: int) -> float:
    """1 when a relevant item is among the first ``k`` returned, else 0."""
    return 1.0 if _hits(np.asarray(rel, dtype=bool), k) > 0 else 0.0


def nearest_neighbour(rel: Sequence[bool]) -> float:
    """NN: precision of the first returned item."""
    return 1.0 if len(rel) and bool(rel[0]) else 0.0


def first_tier(rel: Sequence[bool], n_relevant: int) -> float:
    """FT: recall over the top kappa, kappa = number of relevant items."""
    if n_relevant <= 0:
        return 0.0
    return _hits(np.asarray(rel, dtype=bool), n_relevant) / n_relevant


def second_tier(rel: Sequence[bool], n_relevant: int) -> float:
    """ST: relevant items in the top 2*kappa, over kappa."""
    if n_relevant <= 0:
        return 0.0
    return _hits(np.asarray(rel, dtype=bool), 2 * n_relevant) / n_relevant


def f_measure(rel: Sequence[bool], n_relevant: int, at: int = F_AT) -> float:
    """F: harmonic mean of precision (hits / at) and recall (hits / kappa) over the top ``at``."""
    hits = _hits(np.asarray(rel, dtype=bool), at)
    if hits == 0 or n_relevant <= 0:
        return 0.0
    p, r = hits / at, hits / n_relevant
    return 2 * p * r / (p + r)


def _discounts(n: int) -> np.ndarray:
    # rank 1 is undiscounted, rank i >= 2 is divided by log2(i)
    d = np.ones(n)
    if n > 1:
        d[1:] = 1.0 / np.log2(np.arange(2, n + 1))
    return d


def dcg(rel: Sequence[bool], n_relevant: int) -> float:
    """Normalised DCG over the top K = 2*kappa: sum rel_i / log2(i) (rank 1 undiscounted) over its ideal."""
    if n_relevant <= 0:
        return 0.0
    k = 2 * n_relevant
    gains = np.zeros(k)
    r = np.asarray(rel[:k], dtype=np.float64)
    gains[: len(r)] = r
    disc = _discounts(k)
    return float((gains * disc).sum() / disc[:n_relevant].sum())


def nmrr(rel: Sequence[bool], n_relevant: int) -> float:
    """MPEG-7 NMRR with K = 2*NG: 0 is perfect, 1 means no relevant item within the top K.

    Rank(k) is the rank of the k-th relevant item when <= K, else 1.25*K; AVR = mean Rank;
    MRR = AVR - 0.5 - NG/2; NMRR = MRR / (1.25*K - 0.5 - NG/2).
    """
    ng = n_relevant
    if ng <= 0:
        return 1.0
    k = 2 * ng
    found = [int(i) + 1 for i in np.flatnonzero(np.asarray(rel[:k], dtype=bool))]
    ranks = found + [1.25 * k] * (ng - len(found))
    avr = sum(ranks) / ng
    return (avr - 0.5 - ng / 2) / (1.25 * k - 0.5 - ng / 2)


def first_relevant_rank(rel: Sequence[bool]) -> int | None:
    """1-based rank of the first relevant returned item (``None`` when none was returned)."""
    idx = np.flatnonzero(np.asarray(rel, dtype=bool))
    return int(idx[0]) + 1 if len(idx) else None


def query_metrics(
    rel: Sequence[bool],
    n_relevant: int,
    map_ks: Iterable[int] = MAP_KS,
    top_ks: Iterable[int] = TOP_KS,
    map_normaliser: str = "min",
) -> dict[str, float]:
    """Every metric of one query (``nmrr`` is averaged into ANMRR by :func:`aggregate`)."""
    rel = np.asarray(rel, dtype=bool)
    out: dict[str, float] = {}
    for k in map_ks:
        out[f"mAP@{k}"] = average_precision_at_k(rel, n_relevant, k, map_normaliser)
    out["AP"] = average_precision(rel, n_relevant)
    for k in top_ks:
        out[f"top{k}"] = top_k_hit(rel, k)
    out.update(
        NN=nearest_neighbour(rel),
        FT=first_tier(rel, n_relevant),
        ST=second_tier(rel, n_relevant),
        F=f_measure(rel, n_relevant),
        DCG=dcg(rel, n_relevant),
        NMRR=nmrr(rel, n_relevant),
    )
    return out


def aggregate(per_query: Sequence[dict[str, float]]) -> dict[str, float]:
    """Mean of each metric over queries; ``NMRR`` becomes ``ANMRR``; adds ``n``."""
    if not per_query:
        return {"n": 0}
    out: dict[str, float] = {}
    for key in per_query[0]:
        vals = [q[key] for q in per_query if q.get(key) is not None]
        name = "ANMRR" if key == "NMRR" else key
        out[name] = float(np.mean(vals)) if vals else math.nan
    out["n"] = len(per_query)
    return out


#: Metrics where lower is better (everything else: higher is better).
LOWER_IS_BETTER = frozenset({"ANMRR", "NMRR"})
HEADLINE = ("mAP@1", "mAP@3", "mAP@5", "mAP@10", "top1", "top5", "NN", "FT", "ST", "F", "DCG", "ANMRR")


def headline(metric_set: str) -> tuple[str, ...]:
    """The report's headline columns of a metric set."""
    from pipeline.evaluate import metrics_paper

    return metrics_paper.HEADLINE if metric_set == "paper" else HEADLINE


def aggregate_set(metric_set: str, per_query: Sequence[dict]) -> dict[str, float]:
    """:func:`aggregate` of ``metric_set`` (the paper set counts MI3DOR queries and reports NN in %)."""
    from pipeline.evaluate import metrics_paper

    return metrics_paper.aggregate(per_query) if metric_set == "paper" else aggregate(per_query)


def check_metric_set(name: str) -> str:
    if name not in METRIC_SETS:
        raise ValueError(f"unknown metric set {name!r}; choose from {', '.join(METRIC_SETS)}")
    return name

"""Both metric sets against hand-worked examples and against independent implementations on random rankings.

The independent implementations below are written from the text of the definitions (DESIGN.md's "reference
scripts' metrics" for ``paper``, docs/evaluation.md's formulas for ``standard``), with plain loops, and do
not import the product's metric code. Each takes the raw ranking: (label, score) items in the order the
system returned them, ties ordered pessimistically (non-relevant items of a tied run first).
"""

from __future__ import annotations

import math
import random

import numpy as np
import pytest

from pipeline.evaluate import metrics as M
from pipeline.evaluate import metrics_paper as P

approx = pytest.approx


# ----------------------------------------------------------------------------- independent implementations
def _order(items, relevant):
    """Items sorted by score, best first; within equal scores the non-relevant ones first (pessimistic)."""
    out, i = [], 0
    while i < len(items):
        j = i
        while j < len(items) and items[j][1] == items[i][1]:
            j += 1
        run = items[i:j]
        out += [x for x in run if x[0] not in relevant] + [x for x in run if x[0] in relevant]
        i = j
    return [1 if label in relevant else 0 for label, _ in out]


def ref_view_map(rel, k):
    """mAP@k as the reference: walk the top k, record hits/rank at each hit, mean of them (0 if none)."""
    recorded, hits = [], 0
    for rank, r in enumerate(rel[:k], start=1):
        if r:
            hits += 1
            recorded.append(hits / rank)
    return sum(recorded) / len(recorded) if recorded else 0.0


def ref_mi3dor(rel):
    """NN, FT, ST, F, nDCG, AP, NMRR as DESIGN.md defines them; None when kappa = 0."""
    n, kappa = len(rel), sum(rel)
    if kappa == 0:
        return None
    big_k = min(2 * kappa, n)
    top20 = min(20, n)
    hits20 = sum(rel[:top20])
    prec, rec = hits20 / top20, hits20 / kappa
    f = 0.0 if prec + rec == 0 else 2 * prec * rec / (prec + rec)
    dcg = sum(rel[i - 1] / math.log2(i + 1) for i in range(1, big_k + 1))
    idcg = sum(1 / math.log2(i + 1) for i in range(1, min(kappa, big_k) + 1))
    precisions, hits = [], 0
    for i, r in enumerate(rel, start=1):
        if r:
            hits += 1
            precisions.append(hits / i)
    ranks = [i for i in range(1, big_k + 1) if rel[i - 1]]
    ranks += [big_k + 1] * (kappa - len(ranks))
    avr = sum(ranks) / kappa
    denom = big_k - (kappa + 1) / 2
    nmrr = (avr - (kappa + 1) / 2) / denom if denom > 0 else 0.0
    return {
        "NN": float(rel[0]),
        "FT": sum(rel[:kappa]) / kappa,
        "ST": sum(rel[:big_k]) / kappa,
        "F": f,
        "nDCG": dcg / idcg,
        "AP": sum(precisions) / kappa,
        "NMRR": nmrr,
    }


def ref_standard(rel, n_rel, map_ks=(1, 3, 5, 10)):
    """docs/evaluation.md's textbook set: R = relevant items in the library (some may be missing)."""
    out = {}
    for k in map_ks:
        found, s = 0, 0.0
        for i, r in enumerate(rel[:k], start=1):
            if r:
                found += 1
                s += found / i
        out[f"mAP@{k}"] = s / min(k, n_rel)
    found, s = 0, 0.0
    for i, r in enumerate(rel, start=1):
        if r:
            found += 1
            s += found / i
    out["AP"] = s / n_rel
    out["top1"] = float(any(rel[:1]))
    out["top5"] = float(any(rel[:5]))
    out["NN"] = float(bool(rel) and rel[0] == 1)
    out["FT"] = sum(rel[:n_rel]) / n_rel
    out["ST"] = sum(rel[: 2 * n_rel]) / n_rel
    h = sum(rel[:20])
    p, r = h / 20, h / n_rel
    out["F"] = 0.0 if h == 0 else 2 * p * r / (p + r)
    big_k = 2 * n_rel
    gains = (rel + [0] * big_k)[:big_k]
    dcg = gains[0] + sum(gains[i - 1] / math.log2(i) for i in range(2, big_k + 1))
    ideal = 1 + sum(1 / math.log2(i) for i in range(2, n_rel + 1))
    out["DCG"] = dcg / ideal
    ranks = [i for i in range(1, big_k + 1) if i <= len(rel) and rel[i - 1]]
    ranks += [1.25 * big_k] * (n_rel - len(ranks))
    avr = sum(ranks) / n_rel
    out["NMRR"] = (avr - 0.5 - n_rel / 2) / (1.25 * big_k - 0.5 - n_rel / 2)
    return out


def _random_ranking(rng: random.Random):
    """A ranking of labelled items with many ties (scores on a coarse grid), sorted by score as a system
    returns it (tied items in arbitrary order); sometimes truncated, sometimes without the query's label."""
    n = rng.randint(1, 60)
    labels = [rng.choice("abcdefg") for _ in range(n)]
    scores = [rng.choice([0.1, 0.2, 0.3, 0.5, 0.5, 0.8]) for _ in range(n)]
    items = sorted(zip(labels, scores, strict=True), key=lambda x: -x[1])  # stable: ties keep random order
    gt = rng.choice("abcdefgz")  # "z" never occurs: a miss
    return items, gt


# ----------------------------------------------------------------------------- random rankings
def test_paper_set_matches_an_independent_implementation_on_1000_random_rankings():
    rng = random.Random(13)
    misses = kappa_zero = 0
    for _ in range(1000):
        items, gt = _random_ranking(rng)
        want_rel = _order(items, {gt})
        got_rel = M.relevance_vector([x[0] for x in items], {gt}, [x[1] for x in items], "pessimistic")
        assert got_rel.astype(int).tolist() == want_rel
        got = P.query_metrics(got_rel, got_rel)  # the same ranking as views and as items
        for k in (1, 3, 5, 10):
            assert got[f"mAP@{k}"] == approx(ref_view_map(want_rel, k), abs=1e-12)
        ref = ref_mi3dor(want_rel)
        if ref is None:
            kappa_zero += 1
            assert all(got[key] is None for key in P.MI3DOR_KEYS)
            continue
        for key, value in ref.items():
            assert got[key] == approx(value, abs=1e-12), key
        misses += sum(want_rel[: min(2 * sum(want_rel), len(want_rel))]) < sum(want_rel)
    assert kappa_zero > 50 and misses > 50  # the sample exercises both kinds of miss


def test_standard_set_matches_an_independent_implementation_on_1000_random_rankings():
    rng = random.Random(7)
    for _ in range(1000):
        items, gt = _random_ranking(rng)
        # R counts the library's relevant items, some of which the (truncated) ranking may lack
        n_rel = sum(1 for label, _ in items if label == gt) + rng.randint(0 if gt != "z" else 1, 3)
        if n_rel == 0:
            n_rel = 1
        want_rel = _order(items, {gt})
        got_rel = M.relevance_vector([x[0] for x in items], {gt}, [x[1] for x in items])
        got = M.query_metrics(got_rel, n_rel)
        for key, value in ref_standard(want_rel, n_rel).items():
            assert got[key] == approx(value, abs=1e-12), key


# ----------------------------------------------------------------------------- hand-worked examples
def test_paper_map_ranks_views_with_the_hits_normaliser():
    # views of: B B A C A A (relevant: A): hits at ranks 3, 5, 6
    rel = [0, 0, 1, 0, 1, 1]
    assert P.view_ap_at_k(rel, 1) == 0.0
    assert P.view_ap_at_k(rel, 3) == approx(1 / 3)  # one hit: P = 1/3
    assert P.view_ap_at_k(rel, 5) == approx((1 / 3 + 2 / 5) / 2)
    assert P.view_ap_at_k(rel, 10) == approx((1 / 3 + 2 / 5 + 3 / 6) / 3)
    # the paper's effect: mAP@k can fall as k grows (a late hit lowers the mean)
    falling = [1, 0, 0, 0, 1]
    assert P.view_ap_at_k(falling, 1) == 1.0 and P.view_ap_at_k(falling, 5) == approx((1 + 2 / 5) / 2)


def test_paper_mi3dor_hand_worked():
    # ranking of 6 items, relevant at ranks 1, 3, 6: kappa 3, N 6, K = min(6, 6) = 6
    rel = [1, 0, 1, 0, 0, 1]
    m = P.mi3dor(rel)
    assert m["NN"] == 1.0
    assert m["FT"] == approx(2 / 3)  # 2 hits in the top 3
    assert m["ST"] == approx(1.0)  # 3 hits in the top 6
    p, r = 3 / 6, 3 / 3  # top min(20, 6) = 6
    assert m["F"] == approx(2 * p * r / (p + r))
    dcg = 1 / math.log2(2) + 1 / math.log2(4) + 1 / math.log2(7)
    idcg = 1 / math.log2(2) + 1 / math.log2(3) + 1 / math.log2(4)
    assert m["nDCG"] == approx(dcg / idcg)
    assert m["AP"] == approx((1 + 2 / 3 + 3 / 6) / 3)
    # AVR = (1 + 3 + 6) / 3; NMRR = (AVR - 2) / (6 - 2)
    assert m["NMRR"] == approx((10 / 3 - 2) / 4)


def test_paper_mi3dor_miss_and_short_ranking():
    # kappa 2, N 3 -> K = min(4, 3) = 3; relevant at rank 3 only within K... and rank 3 is the 2nd
    rel = [0, 1, 1]
    m = P.mi3dor(rel)
    assert m["FT"] == approx(1 / 2) and m["ST"] == approx(1.0)
    assert m["F"] == approx(2 * (2 / 3) * 1 / (2 / 3 + 1))  # top min(20, 3) = 3
    # AVR = (2 + 3) / 2 = 2.5; NMRR = (2.5 - 1.5) / (3 - 1.5)
    assert m["NMRR"] == approx(1 / 1.5)
    # a relevant item beyond K counts as K + 1: kappa 1, N 5, K 2, rank 4 -> AVR 3 -> (3 - 1) / (2 - 1) = 2
    assert P.mi3dor([0, 0, 0, 1, 0])["NMRR"] == approx(2.0)
    # denominator <= 0 -> 0: kappa 1, N 1 -> K 1, 1 - 1 = 0
    assert P.mi3dor([1])["NMRR"] == 0.0
    assert P.mi3dor([0, 0]) is None and P.mi3dor([]) is None  # kappa 0: not counted


def test_paper_aggregate_counts_queries_and_reports_nn_in_percent():
    q1 = P.query_metrics([1, 0], [1, 0])
    q2 = P.query_metrics([0, 1], [0, 1])
    q3 = P.query_metrics([0, 0], [0, 0])  # a miss: counted by mAP@k (0), not by the MI3DOR measures
    agg = P.aggregate([q1, q2, q3])
    assert agg["n"] == 3 and agg["n_mi3dor"] == 2
    assert agg["mAP@1"] == approx(1 / 3) and agg["mAP@3"] == approx((1 + 1 / 2 + 0) / 3)
    assert agg["NN"] == approx(50.0) and agg["FT"] == approx(0.5)
    # q1: kappa 1, K 2, rank 1 -> 0; q2: rank 2 -> (2 - 1) / (2 - 1) = 1
    assert agg["ANMRR"] == approx(0.5) and "NMRR" not in agg
    assert M.aggregate_set("paper", [q1])["NN"] == approx(100.0)
    assert M.aggregate_set("standard", [M.query_metrics([1], 1)])["NN"] == approx(1.0)


def test_the_sets_differ_where_the_issue_says():
    # one relevant mesh at rank 2 of 10: standard DCG = 1/log2(2) / 1 = 1 (top-2 accuracy); paper nDCG uses
    # log2(i + 1): (1 / log2(3)) / (1 / log2(2))
    rel = [0, 1] + [0] * 8
    assert M.dcg(rel, 1) == approx(1.0)
    assert P.mi3dor(rel)["nDCG"] == approx(1 / math.log2(3))
    # ANMRR: MPEG-7 (standard) K = 2, rank 2 -> (2 - 1) / (2.5 - 1) = 2/3; reference: (2 - 1) / (2 - 1) = 1
    assert M.nmrr(rel, 1) == approx(2 / 3) and P.mi3dor(rel)["NMRR"] == approx(1.0)


def test_metric_set_names_are_checked():
    assert M.check_metric_set("paper") == "paper"
    with pytest.raises(ValueError, match="metric set"):
        M.check_metric_set("bop")
    from pipeline.evaluate.sweep import MetricOptions

    with pytest.raises(ValueError, match="metric set"):
        MetricOptions(metric_set="textbook")
    assert MetricOptions().metric_set == "paper" and MetricOptions().views


def test_vectorised_ties_match_on_two_column_keys():
    rng = np.random.default_rng(3)
    for _ in range(200):
        n = int(rng.integers(1, 30))
        ids = [str(int(x)) for x in rng.integers(0, 5, n)]
        keys = np.round(rng.random((n, 2)) * 3) / 3  # many exact ties on both columns
        keys = keys[np.lexsort((-keys[:, 1], -keys[:, 0]))]
        got = M.relevance_vector(np.array(ids, dtype=object), {"1"}, keys, "pessimistic")
        tuples = [tuple(k) for k in keys.tolist()]
        want = _order(list(zip(ids, tuples, strict=True)), {"1"})
        assert got.astype(int).tolist() == want

"""Every metric against values computed by hand on tiny rankings (docs/evaluation.md has the formulas)."""

from __future__ import annotations

import math

import pytest

from pipeline.evaluate import metrics as M

approx = pytest.approx


def test_two_relevant_at_ranks_2_and_4():
    rel, r = [0, 1, 0, 1, 0], 2
    assert M.average_precision_at_k(rel, r, 1) == 0.0
    assert M.average_precision_at_k(rel, r, 3) == approx(0.5 / 2)  # P(2)=1/2, Z=min(3,2)=2
    assert M.average_precision_at_k(rel, r, 5) == approx((1 / 2 + 2 / 4) / 2)
    assert M.average_precision_at_k(rel, r, 10) == approx(0.5)
    assert M.average_precision(rel, r) == approx(0.5)
    assert M.average_precision_at_k(rel, r, 3, "hits") == approx(0.5)  # Z = hits in top 3 = 1
    assert M.average_precision_at_k(rel, r, 3, "relevant") == approx(0.25)
    assert M.top_k_hit(rel, 1) == 0.0 and M.top_k_hit(rel, 5) == 1.0
    assert M.nearest_neighbour(rel) == 0.0
    assert M.first_tier(rel, r) == approx(0.5)  # 1 hit in the top 2
    assert M.second_tier(rel, r) == approx(1.0)  # 2 hits in the top 4
    p, rc = 2 / 20, 2 / 2
    assert M.f_measure(rel, r) == approx(2 * p * rc / (p + rc))
    assert M.dcg(rel, r) == approx((1 / math.log2(2) + 1 / math.log2(4)) / (1 + 1 / math.log2(2)))
    # NMRR: K=4, ranks 2 and 4, AVR=3, MRR=3-0.5-1=1.5, norm=1.25*4-0.5-1=3.5
    assert M.nmrr(rel, r) == approx(1.5 / 3.5)


def test_single_relevant_at_rank_3():
    rel, r = [0, 0, 1, 0, 0, 0], 1
    assert M.average_precision_at_k(rel, r, 1) == 0.0
    assert M.average_precision_at_k(rel, r, 3) == approx(1 / 3)
    assert M.average_precision_at_k(rel, r, 5) == approx(1 / 3)
    assert M.top_k_hit(rel, 5) == 1.0
    assert M.first_tier(rel, r) == 0.0 and M.second_tier(rel, r) == 0.0
    assert M.f_measure(rel, r) == approx(2 * 0.05 * 1 / 1.05)
    assert M.dcg(rel, r) == 0.0  # K = 2: rank 3 is outside
    # not within K=2 -> Rank = 1.25*2 = 2.5; MRR = 2.5-0.5-0.5 = 1.5; norm = 2.5-0.5-0.5 = 1.5
    assert M.nmrr(rel, r) == approx(1.0)
    assert M.first_relevant_rank(rel) == 3


def test_perfect_ranking_scores_one_and_nmrr_zero():
    rel, r = [1, 1, 1, 0], 3
    q = M.query_metrics(rel, r)
    for key in ("mAP@1", "mAP@3", "mAP@5", "mAP@10", "AP", "top1", "top5", "NN", "FT", "ST", "DCG"):
        assert q[key] == approx(1.0), key
    assert q["NMRR"] == approx(0.0)
    assert q["F"] == approx(2 * (3 / 20) * 1 / (3 / 20 + 1))


def test_relevant_items_missing_from_a_truncated_ranking():
    rel, r = [0, 1], 3  # two of the three relevant models were never returned
    assert M.first_tier(rel, r) == approx(1 / 3)
    assert M.second_tier(rel, r) == approx(1 / 3)
    assert M.average_precision_at_k(rel, r, 5) == approx((1 / 2) / 3)
    assert M.average_precision(rel, r) == approx((1 / 2) / 3)
    ideal = 1 + 1 + 1 / math.log2(3)
    assert M.dcg(rel, r) == approx(1.0 / ideal)
    # K = 6: ranks 2, 7.5, 7.5 -> AVR = 17/3; MRR = 17/3 - 0.5 - 1.5; norm = 7.5 - 2
    assert M.nmrr(rel, r) == approx((17 / 3 - 2) / 5.5)


def test_empty_ranking_and_no_relevant():
    assert M.query_metrics([], 1)["NMRR"] == approx(1.0)
    assert M.query_metrics([], 1)["mAP@5"] == 0.0
    assert M.first_relevant_rank([0, 0]) is None
    assert M.first_tier([1], 0) == 0.0


def test_ties_are_ordered_by_policy():
    ids, scores = ["a", "b", "c", "d"], [0.9, 0.5, 0.5, 0.1]
    assert M.relevance_vector(ids, {"b"}, scores, "pessimistic").tolist() == [0, 0, 1, 0]
    assert M.relevance_vector(ids, {"b"}, scores, "optimistic").tolist() == [0, 1, 0, 0]
    assert M.relevance_vector(ids, {"c"}, scores, "list").tolist() == [0, 0, 1, 0]
    assert M.relevance_vector(ids, {"c"}, scores, "optimistic").tolist() == [0, 1, 0, 0]
    # a constant-score system earns nothing under the pessimistic policy
    flat = [0.5] * 4
    assert M.top_k_hit(M.relevance_vector(ids, {"a"}, flat), 1) == 0.0
    assert M.top_k_hit(M.relevance_vector(ids, {"a"}, flat, "optimistic"), 1) == 1.0
    # two relevant in a tie of three
    v = M.relevance_vector(["a", "b", "c"], {"a", "c"}, [0.3, 0.3, 0.3])
    assert v.tolist() == [0, 1, 1]
    assert M.average_precision(v, 2) == approx((1 / 2 + 2 / 3) / 2)
    assert M.relevance_vector(["a", "b", "c"], {"a", "c"}, [0.3] * 3, "optimistic").tolist() == [1, 1, 0]
    # NaN scores (a candidate without a score) never tie
    assert M.relevance_vector(["a", "b"], {"b"}, [float("nan"), float("nan")]).tolist() == [0, 1]
    # sort keys may be tuples (two-stage: image score, then text score)
    keys = [(0.5, 0.3), (0.5, 0.3), (0.5, 0.2)]
    assert M.relevance_vector(["a", "b", "c"], {"a"}, keys).tolist() == [0, 1, 0]
    assert M.relevance_vector(["a", "b", "c"], {"c"}, keys).tolist() == [0, 0, 1]
    with pytest.raises(ValueError):
        M.relevance_vector(ids, {"a"}, scores, "random")


def test_aggregate_means_and_anmrr():
    q1 = M.query_metrics([1, 0, 0], 1)
    q2 = M.query_metrics([0, 0, 1], 1)
    agg = M.aggregate([q1, q2])
    assert agg["n"] == 2
    assert agg["mAP@1"] == approx(0.5)
    assert agg["mAP@3"] == approx((1 + 1 / 3) / 2)
    assert agg["top1"] == approx(0.5)
    assert agg["ANMRR"] == approx((0.0 + 1.0) / 2)
    assert "NMRR" not in agg
    assert M.aggregate([]) == {"n": 0}


def test_unknown_normaliser_is_an_error():
    with pytest.raises(ValueError, match="normaliser"):
        M.average_precision_at_k([1], 1, 1, "median")

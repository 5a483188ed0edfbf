"""Open-set calibration: fit and cross-validate the acceptance models of :mod:`pipeline.query.accept`.

The split: every query is answered against the full store (its top-1 is right or wrong), and the queries
of the objects left out (by default the 21 YCB-Video objects) are answered again against the store without
those objects (:func:`pipeline.evaluate.openset_split.without_meshes`), where every top-1 is wrong. A
query whose expected mesh is not in the store at all counts as absent against the full store.

Per ranking variant (mode, verified or not) a logistic model of P(top-1 right | answer features) is fitted
(scikit-learn, standardised features; each query file weighs the same in total, so a few real photos are
not drowned by many synthetic renders). Its features are picked by greedy forward selection, scored by
the absent answers rejected at the target acceptance in grouped 5-fold cross-validation of the training
answers only (:func:`select_features`). Everything reported is out of fold: leave one object out (all
answers of an object, with and without it in the library, in the same fold); inside each fold the
operating point is the highest threshold that still accepts ``target`` of the *training* folds' correct
answers, weighted as in the fit (each query file's correct answers weigh the same in total, so the
threshold is not set by the synthetic renders alone, which score higher than real photos). The shipped
model is then fitted on all answers with the same rule.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

#: the 21 objects of the YCB-Video dataset, as YCB class labels
YCB_VIDEO_LABELS = (
    "002", "003", "004", "005", "006", "007", "008", "009", "010", "011", "019",
    "021", "024", "025", "035", "036", "037", "040", "051", "052", "061",
)  # fmt: skip
#: ranking variants answered per query: (mode, verify)
RANKINGS = (("two-stage", True), ("two-stage", False), ("image-only", True), ("image-only", False),
            ("text-only", False))  # fmt: skip
CURVE = tuple(round(t, 2) for t in np.arange(0.0, 1.0001, 0.05))
#: the forward selection adds a feature only when it raises the inner cross-validated rejection by this much
#: (2 points, about one standard error of a paired difference here, did no better on a fresh set:
#: docs/results.md, section 6.6)
MIN_GAIN = 0.005
#: fold assignments the feature selection votes over (:func:`select_features`)
REPEATS = 5


@dataclass
class Example:
    """One answer: its features, and whether its top-1 was right."""

    query_id: str
    group: str  # cross-validation group: the object (class label, else the expected mesh)
    source: str  # the query file it came from
    roi: str  # "mask" | "box"
    library: str  # "full" | "absent" (the query's object left out of the library)
    variant: str
    features: dict[str, float | None]
    correct: bool
    top1: str | None
    confidence: float | None = None  # out of fold (filled by cross_validate)
    accepted: bool | None = None  # out of fold, at the fold's operating point
    weight_group: str | None = None  # query files weighed together (``--weigh-together``); None: its file

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


def load_examples(
    paths: list[str | Path],
    variant: str | None = None,
    rois: tuple[str, ...] | None = None,
    together: set[str] | frozenset[str] = frozenset(),
) -> list[Example]:
    """The answers written one JSON line each (``Example.to_json``, as ``python -m pipeline.evaluate
    openset`` and ``bench/openset_examples.py`` write them) in ``paths``, of ``variant`` and the ROI kinds
    ``rois`` only when given; features no longer offered are dropped, and the sources in ``together`` share
    one weight group."""
    from pipeline.query.accept import FEATURES

    out = []
    for p in paths:
        for line in Path(p).read_text(encoding="utf-8").splitlines():
            if not line.strip():
                continue
            e = Example(**json.loads(line))
            if (variant is not None and e.variant != variant) or (rois is not None and e.roi not in rois):
                continue
            e.features = {k: v for k, v in e.features.items() if k in FEATURES}
            if e.source in together:
                e.weight_group = "+".join(sorted(together))
            out.append(e)
    return out


def collect(
    retriever,
    reduced,
    queries: list,
    library,
    absent_labels: set[str],
    rois: tuple[str, ...] = ("mask", "box"),
    progress: bool = False,
    on_error: Callable[[str, str], None] | None = None,
    embeddings: dict | None = None,
) -> list[Example]:
    """Answer every (query, ROI variant) once per ranking variant, against the full store and, for the
    left-out objects, against ``reduced`` (the store without them). ``embeddings`` (filled and reused,
    keyed by query and ROI variant) spares re-embedding when only the ranking side changed."""
    from pipeline.evaluate.datasets import drop_mask
    from pipeline.evaluate.engine import Engine
    from pipeline.evaluate.sweep import relevance_for
    from pipeline.progress import iterate
    from pipeline.query.errors import QueryError

    engine = Engine(retriever, str(retriever.store.root))
    for r in (retriever, reduced):  # record every feature an answer offers, not only the calibration's
        if getattr(r.ranking, "patches", None) is not None:
            r.ranking.patches.always = True
    out: list[Example] = []
    items = [(q, src, roi) for q, src in queries for roi in rois if roi == "mask" or q.box or q.mask]
    for q, src, roi in iterate(items, "open-set answers", unit="query", enabled=progress):
        rel = relevance_for(q, library)
        inst = rel.instance if rel else set()
        absent = q.label in absent_labels or (
            bool(inst) and all(library.labels.get(m) in absent_labels for m in inst)
        )
        group = q.label or (sorted(q.expected)[0] if q.expected else q.query_id)
        key = (src, q.query_id, roi, q.image, q.mask, q.box, q.prompt)
        try:
            emb = embeddings.get(key) if embeddings is not None else None
            if emb is None:
                emb = engine.embed(q if roi == "mask" else drop_mask(q), "segm").embedding
                emb.inliers = {}
                if embeddings is not None:
                    embeddings[key] = emb
        except QueryError as exc:
            if on_error:
                on_error(q.query_id, str(exc))
            continue
        emb = dataclasses.replace(emb, inliers={})
        targets = [(retriever, emb, bool(inst))]
        if absent and reduced is not None:  # the inlier cache is keyed by the store's mesh_idx
            targets.append((reduced, dataclasses.replace(emb, inliers={}), False))
        for r, e, present in targets:
            for mode, verify in RANKINGS:
                res = r.rank(e, mode=mode, top=2, verify=verify)
                best = res.best.mesh_id if res.best else None
                v = res.verdict
                lib = "full" if present else "absent"
                out.append(
                    Example(q.query_id, group, src, roi, lib, v.variant, dict(v.features), best in inst, best)
                )
    return _dedupe(out)


def _dedupe(examples: list[Example]) -> list[Example]:
    """One example per (query, roi, library, variant): a store without local features answers the
    ``+verify`` rankings unverified, which would count those answers twice."""
    seen, out = set(), []
    for e in examples:
        key = (e.query_id, e.source, e.roi, e.library, e.variant)
        if key not in seen:
            seen.add(key)
            out.append(e)
    return out


# ---------------------------------------------------------------------------- fitting
def _matrix(examples: list[Example], features: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    x = np.array([[e.features[f] for f in features] for e in examples], np.float64)
    y = np.array([e.correct for e in examples], bool)
    return x, y


def _weights(examples: list[Example]) -> np.ndarray:
    """Each query file, or group of files weighed together (``weight_group``: the real photos, say), weighs
    the same in total (mean weight 1)."""
    sources = [e.weight_group or e.source for e in examples]
    counts = {s: sources.count(s) for s in set(sources)}
    w = np.array([1.0 / counts[s] for s in sources])
    return w * len(w) / w.sum()


def usable_features(examples: list[Example]) -> tuple[str, ...]:
    """The features every example of a variant has (a variant without stage 1 has no text score...)."""
    from pipeline.query.accept import FEATURES

    return tuple(f for f in FEATURES if all(e.features.get(f) is not None for e in examples))


def fit(examples: list[Example], features: tuple[str, ...], target: float, c: float = 1.0):
    """A logistic :class:`~pipeline.query.accept.AcceptModel` on ``examples`` with the operating point
    that accepts ``target`` of their correct answers."""
    from sklearn.linear_model import LogisticRegression

    from pipeline.query.accept import AcceptModel

    x, y = _matrix(examples, features)
    w = _weights(examples)
    mean = np.average(x, axis=0, weights=w)
    scale = np.sqrt(np.average((x - mean) ** 2, axis=0, weights=w))
    scale = np.where(scale > 1e-9, scale, 1.0)
    if y.all() or not y.any():
        raise ValueError("calibration needs both right and wrong answers")
    lr = LogisticRegression(C=c, max_iter=1000)
    lr.fit((x - mean) / scale, y, sample_weight=w)
    model = AcceptModel(
        features=features,
        mean=tuple(float(v) for v in mean),
        scale=tuple(float(v) for v in scale),
        coef=tuple(float(v) for v in lr.coef_[0]),
        intercept=float(lr.intercept_[0]),
        threshold=0.0,
    )
    return dataclasses.replace(model, threshold=operating_point(model.predict(x[y]), target, w[y]))


def operating_point(correct_conf: np.ndarray, target: float, weights: np.ndarray | None = None) -> float:
    """The highest threshold t with at least ``target`` of ``correct_conf`` >= t (rounded down to 1e-4);
    with ``weights``, ``target`` is a share of the correct answers' total weight."""
    conf = np.asarray(correct_conf, np.float64)
    if not len(conf):
        return 0.5
    order = np.argsort(conf, kind="stable")
    c = conf[order]
    w = np.ones(len(c)) if weights is None else np.asarray(weights, np.float64)[order]
    below = np.cumsum(w) / w.sum()  # share of the weight at or below each answer
    # the answers that may be refused: the lowest ones whose weight stays within 1 - target
    k = int(np.searchsorted(below, 1.0 - target + 1e-9, side="right"))
    return math.floor(c[min(k, len(c) - 1)] * 1e4) / 1e4


def rejected_at_target(examples: list[Example], conf: np.ndarray, target: float) -> float:
    """Share of the absent answers rejected at the threshold that accepts ``target`` of the correct ones
    (counted, not weighted: the feature selection's criterion; weighting it by query file, so that 21 photo
    objects decide it, made the selection keep only score and inliers and reject less out of fold)."""
    right = np.array([e.library == "full" and e.correct for e in examples])
    absent = np.array([e.library == "absent" for e in examples])
    if not right.any() or not absent.any():
        return 0.0
    t = operating_point(conf[right], target)
    return float((conf[absent] < t).mean())


def select_features(
    examples: list[Example],
    candidates: tuple[str, ...],
    target: float,
    c: float = 1.0,
    folds: int = 5,
    min_gain: float = MIN_GAIN,
    repeats: int = REPEATS,
) -> tuple[str, ...]:
    """The feature set picked most often by :func:`greedy_selection` over ``repeats`` fold assignments of
    the groups (each a seeded relabelling of the groups before grouped ``folds``-fold splitting); a tie goes
    to the set with fewer features, then to the one found first. One assignment alone was unstable: 58
    leave-one-object-out folds picked 11 different sets, and out of fold that instability cost more
    rejection than any feature added (docs/results.md, section 6.7)."""
    from collections import Counter

    names = sorted({e.group for e in examples})
    votes: Counter = Counter()
    for r in range(max(int(repeats), 1)):
        rank = dict(zip(names, np.random.default_rng(r).permutation(len(names)).tolist(), strict=True))
        groups = np.array([rank[e.group] for e in examples])
        votes[greedy_selection(examples, candidates, target, groups, c, folds, min_gain)] += 1
    top = max(votes.values())
    return min((feats for feats, n in votes.items() if n == top), key=len)


def greedy_selection(
    examples: list[Example],
    candidates: tuple[str, ...],
    target: float,
    groups: np.ndarray,
    c: float = 1.0,
    folds: int = 5,
    min_gain: float = MIN_GAIN,
) -> tuple[str, ...]:
    """Greedy forward selection from no feature: add the candidate that most raises the absent answers
    rejected at ``target`` acceptance of the correct ones, measured by ``folds``-fold cross-validation
    inside ``examples`` grouped by ``groups`` (one label per example); stop when no candidate adds at
    least ``min_gain``. The first feature is the best single one, not a fixed ``score``: once the learned
    cosine drives the ranking, the raw score shifts between real photos and renders more than its
    normalised ``score_z`` does, and a selection forced to start from it kept it (docs/results.md, 6.3)."""
    from sklearn.model_selection import GroupKFold

    k = min(folds, len(set(groups.tolist())))
    splits = list(GroupKFold(n_splits=k).split(np.zeros(len(groups)), groups=groups)) if k >= 2 else []

    def score(feats: tuple[str, ...]) -> float:
        conf = np.zeros(len(examples))
        for train, test in splits:
            tr = [examples[i] for i in train]
            try:
                m = fit(tr, feats, target, c)
            except ValueError:  # a fold with only right (or only wrong) answers
                return -1.0
            conf[test] = m.predict(_matrix([examples[i] for i in test], feats)[0])
        return rejected_at_target(examples, conf, target)

    if not splits:
        return ("score",) if "score" in candidates else tuple(candidates[:1])
    chosen: tuple[str, ...] = ()
    best = -1.0
    while True:
        trials = [(score((*chosen, f)), f) for f in candidates if f not in chosen]
        if not trials:
            return chosen
        value, f = max(trials, key=lambda t: (t[0], -candidates.index(t[1])))
        if chosen and value < best + min_gain:
            return chosen
        chosen, best = (*chosen, f), value


def cross_validate(
    examples: list[Example],
    features: tuple[str, ...],
    target: float,
    c: float = 1.0,
    select: bool = False,
    min_gain: float = MIN_GAIN,
    repeats: int = REPEATS,
) -> dict[str, int]:
    """Leave one object out: fill each example's out-of-fold ``confidence`` and ``accepted``. With
    ``select``, each fold picks its features from ``features`` on its training folds alone
    (:func:`select_features` with ``min_gain`` and ``repeats``); returns how often each feature set was
    picked."""
    groups = sorted({e.group for e in examples})
    picked: dict[str, int] = {}
    for g in groups:
        train = [e for e in examples if e.group != g]
        test = [e for e in examples if e.group == g]
        feats = (
            select_features(train, features, target, c, min_gain=min_gain, repeats=repeats)
            if select
            else features
        )
        picked[",".join(feats)] = picked.get(",".join(feats), 0) + 1
        model = fit(train, feats, target, c)
        x, _ = _matrix(test, feats)
        for e, p in zip(test, model.predict(x), strict=True):
            e.confidence = float(p)
            e.accepted = bool(p >= model.threshold)
    return picked


# ---------------------------------------------------------------------------- report
@dataclass
class Rates:
    """Out-of-fold rates of one slice, with bootstrap intervals (groups resampled)."""

    absent_rejected: dict = field(default_factory=dict)  # {"rate", "lo", "hi", "n"}
    correct_accepted: dict = field(default_factory=dict)
    wrong_rejected: dict = field(default_factory=dict)  # present in the library, but top-1 wrong


def rate(examples: list[Example], pick, hit, reps: int = 1000, seed: int = 0) -> dict:
    """Fraction of ``pick`` examples where ``hit``, with a 95% bootstrap interval over groups."""
    sel = [e for e in examples if pick(e)]
    if not sel:
        return {"rate": None, "lo": None, "hi": None, "n": 0}
    by: dict[str, list[int]] = {}
    for e in sel:
        by.setdefault(e.group, []).append(int(bool(hit(e))))
    keys = sorted(by)
    hits = np.array([sum(by[k]) for k in keys], np.float64)
    ns = np.array([len(by[k]) for k in keys], np.float64)
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(keys), size=(reps, len(keys)))
    boot = hits[idx].sum(1) / ns[idx].sum(1)
    lo, hi = np.quantile(boot, [0.025, 0.975])
    return {"rate": float(hits.sum() / ns.sum()), "lo": float(lo), "hi": float(hi), "n": int(ns.sum())}


def rates_at(examples: list[Example], accepted=None) -> Rates:
    """The three rates at the examples' out-of-fold decisions (or ``accepted(e)``)."""
    acc = accepted or (lambda e: e.accepted)
    return Rates(
        absent_rejected=rate(examples, lambda e: e.library == "absent", lambda e: not acc(e)),
        correct_accepted=rate(examples, lambda e: e.library == "full" and e.correct, acc),
        wrong_rejected=rate(examples, lambda e: e.library == "full" and not e.correct, lambda e: not acc(e)),
    )


def rejection_curve(examples: list[Example], thresholds=CURVE) -> list[dict]:
    """Rates when one global threshold is applied to the out-of-fold confidences."""
    rows = []
    for t in thresholds:
        r = rates_at(examples, lambda e, t=t: e.confidence >= t)
        rows.append({"threshold": t, **{k: v for k, v in dataclasses.asdict(r).items()}})
    return rows


def calibration_error(examples: list[Example], bins: int = 10) -> dict:
    """Brier score and expected calibration error of the out-of-fold confidences."""
    p = np.array([e.confidence for e in examples], np.float64)
    y = np.array([e.correct for e in examples], np.float64)
    if not len(p):
        return {"brier": None, "ece": None}
    which = np.minimum((p * bins).astype(int), bins - 1)
    ece = sum(abs(p[which == b].mean() - y[which == b].mean()) * (which == b).mean() for b in range(bins)
              if (which == b).any())  # fmt: skip
    return {"brier": float(np.mean((p - y) ** 2)), "ece": float(ece)}

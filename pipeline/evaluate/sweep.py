"""Sweeps and ablations: every setting is scored from embeddings computed once per (query, ROI variant).

A sweep varies one knob from the base setting: ``tau`` (stage-1 threshold), ``fallback_k``, ``mode`` and
``roi``. Prompt styles are an onboarding-time setting (captions are re-made per style), so they are compared
across stores by :func:`evaluate_styles`.
"""

from __future__ import annotations

import statistics
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from pipeline.evaluate import metrics as M
from pipeline.evaluate import metrics_paper
from pipeline.evaluate.datasets import Query
from pipeline.evaluate.engine import Embedded, Engine, Ranked, Setting
from pipeline.evaluate.library import Library
from pipeline.query.modes import MODES

ROI_MODES = ("segm", "bbox")
DEFAULT_TAUS = tuple(round(0.10 + 0.05 * i, 2) for i in range(12))  # 0.10 .. 0.65
DEFAULT_TOP_KS = (5, 10, 15, 20, 25, 30, 35, 40)


@dataclass
class SweepPlan:
    base: Setting
    taus: tuple[float, ...] = DEFAULT_TAUS
    top_ks: tuple[int, ...] = DEFAULT_TOP_KS
    modes: tuple[str, ...] = MODES
    rois: tuple[str, ...] = ROI_MODES

    def sweeps(self) -> dict[str, list[Setting]]:
        b = self.base
        return {
            "tau": [replace(b, threshold=t) for t in self.taus],
            "fallback_k": [replace(b, fallback_k=k) for k in self.top_ks],
            "mode": [replace(b, mode=m) for m in self.modes],
            "roi": [replace(b, roi=r) for r in self.rois],
        }

    def settings(self) -> list[Setting]:
        """Every distinct setting, base first."""
        out = [self.base]
        for group in self.sweeps().values():
            out += [s for s in group if s not in out]
        return out


@dataclass
class Relevance:
    """What counts as correct for one query: instance level, and class level when it has a label."""

    instance: set[str]
    klass: set[str] | None


def relevance_for(q: Query, library: Library) -> Relevance | None:
    inst: set[str] = set()
    for e in q.expected:
        inst |= library.resolve(e)
    if not inst:
        return None
    klass = library.with_label(q.label) | inst if q.label else None
    return Relevance(inst, klass)


@dataclass
class MetricOptions:
    ties: str = "pessimistic"
    map_normaliser: str = "min"  # the standard set's mAP@k normaliser (the paper set's is always hits)
    metric_set: str = "paper"  # "paper" (reference scripts' definitions) | "standard" (textbook)

    def __post_init__(self) -> None:
        M.check_metric_set(self.metric_set)

    @property
    def views(self) -> bool:
        """Whether rankings need the view level (the paper set's mAP@k ranks views)."""
        return self.metric_set == "paper"


@dataclass
class SettingResult:
    """Per-query metrics (instance and class level) and retrieval stats of one setting."""

    setting: Setting
    metric_set: str = "paper"
    instance: list[dict] = field(default_factory=list)
    klass: list[dict] = field(default_factory=list)
    fallback: list[bool] = field(default_factory=list)
    n_stage1: list[int] = field(default_factory=list)
    rank_seconds: list[float] = field(default_factory=list)
    threshold_used: float | None = None

    def add(self, ranked: Ranked, rel: Relevance, opts: MetricOptions) -> dict:
        vec = M.relevance_vector(ranked.ids, rel.instance, ranked.scores, opts.ties)
        qm = _query_metrics(ranked, vec, rel.instance, opts)
        self.instance.append(qm)
        if rel.klass is not None:
            cvec = M.relevance_vector(ranked.ids, rel.klass, ranked.scores, opts.ties)
            self.klass.append(_query_metrics(ranked, cvec, rel.klass, opts))
        self.fallback.append(ranked.used_fallback)
        if ranked.n_stage1 is not None:
            self.n_stage1.append(int(ranked.n_stage1))
        self.rank_seconds.append(ranked.seconds)
        if ranked.threshold is not None:
            self.threshold_used = float(ranked.threshold)
        return {"rank": M.first_relevant_rank(vec), **qm}

    def summary(self) -> dict:
        return {
            "setting": self.setting.to_json(),
            "metric_set": self.metric_set,
            "threshold_used": self.threshold_used,
            "instance": M.aggregate_set(self.metric_set, self.instance),
            "class": M.aggregate_set(self.metric_set, self.klass) if self.klass else None,
            "fallback_rate": float(np.mean(self.fallback)) if self.fallback else None,
            "mean_stage1": float(np.mean(self.n_stage1)) if self.n_stage1 else None,
            "mean_rank_ms": 1000 * float(np.mean(self.rank_seconds)) if self.rank_seconds else None,
        }


def _query_metrics(ranked: Ranked, mesh_rel, relevant: set[str], opts: MetricOptions) -> dict:
    """One query's metrics in ``opts.metric_set`` (``mesh_rel``: relevance over the ranked meshes)."""
    if opts.metric_set == "paper":
        if ranked.view_ids is None:
            raise ValueError("the paper metric set needs the view-level ranking (Engine.rank(views=True))")
        view_rel = M.relevance_vector(ranked.view_ids, relevant, ranked.view_keys, opts.ties)
        return metrics_paper.query_metrics(view_rel, mesh_rel)
    return M.query_metrics(mesh_rel, len(relevant), map_normaliser=opts.map_normaliser)


@dataclass
class QueryRecord:
    """What the report keeps per query at the base setting."""

    query: Query
    ranked: Ranked
    rel: Relevance
    metrics: dict
    roi_image: object  # thumbnail (PIL) of the ROI the models saw; kept for failures only


@dataclass
class EvalRun:
    """The outcome of :func:`evaluate`."""

    plan: SweepPlan
    results: dict[Setting, SettingResult]
    records: list[QueryRecord]
    unresolved: list[str]
    failed: list[dict]
    embed_seconds: dict[str, list[float]]

    def summary(self) -> dict:
        base = self.results[self.plan.base].summary()
        sweeps = {
            name: [self.results[s].summary() for s in group] for name, group in self.plan.sweeps().items()
        }
        return {"base": base, "sweeps": sweeps, "timings": self.timings()}

    def timings(self) -> dict:
        out = {}
        for roi, secs in self.embed_seconds.items():
            if secs:
                out[f"roi_embed_{roi}_ms"] = _stats(secs)
        ranks = [s for r in self.results.values() for s in r.rank_seconds]
        if ranks:
            out["rank_ms"] = _stats(ranks)
        return out


def _stats(secs: list[float]) -> dict:
    ms = sorted(1000 * s for s in secs)
    return {
        "mean": round(statistics.fmean(ms), 2),
        "p50": round(ms[len(ms) // 2], 2),
        "p95": round(ms[min(len(ms) - 1, int(0.95 * len(ms)))], 2),
        "n": len(ms),
    }


def evaluate(
    engine: Engine,
    queries: list[Query],
    library: Library,
    plan: SweepPlan,
    opts: MetricOptions | None = None,
    sweeps: bool = True,
    progress: Callable | None = None,
) -> EvalRun:
    """Score ``queries`` at the base setting and (``sweeps``) at every sweep setting."""
    opts = opts or MetricOptions()
    settings = plan.settings() if sweeps else [plan.base]
    if not sweeps:
        plan = replace(plan, taus=(), top_ks=(), modes=(), rois=())
    results = {s: SettingResult(s, opts.metric_set) for s in settings}
    rois = list(dict.fromkeys([plan.base.roi] + [s.roi for s in settings]))
    records: list[QueryRecord] = []
    unresolved: list[str] = []
    failed: list[dict] = []
    embed_seconds: dict[str, list[float]] = {r: [] for r in rois}
    it = progress(queries) if progress else queries
    for q in it:
        rel = relevance_for(q, library)
        if rel is None:
            unresolved.append(q.query_id)
            continue
        embedded: dict[str, Embedded] = {}
        try:
            for roi in rois:
                embedded[roi] = engine.embed(q, roi)
                embed_seconds[roi].append(embedded[roi].seconds)
        except Exception as exc:  # one bad query (unreadable image, empty ROI) must not stop the run
            failed.append({"query_id": q.query_id, "error": f"{type(exc).__name__}: {exc}"[:300]})
            continue
        for s in settings:
            ranked = engine.rank(embedded[s.roi], s, views=opts.views)
            qm = results[s].add(ranked, rel, opts)
            if s == plan.base:
                # keep a thumbnail of the ROI for the failure gallery only (memory stays small)
                thumb = _thumbnail(embedded[s.roi].roi) if qm["rank"] != 1 else None
                records.append(QueryRecord(q, ranked, rel, qm, thumb))
    return EvalRun(plan, results, records, unresolved, failed, embed_seconds)


def group_metrics(records: list[QueryRecord], key: str, metric_set: str = "paper") -> dict[str, dict]:
    """Instance-level base-setting metrics per value of a query field or metadata key (e.g. background)."""
    groups: dict[str, list[dict]] = {}
    for r in records:
        value = getattr(r.query, key, None) if key in ("label", "prompt") else r.query.meta.get(key)
        if value is not None:
            groups.setdefault(str(value), []).append({k: v for k, v in r.metrics.items() if k != "rank"})
    return {v: M.aggregate_set(metric_set, rows) for v, rows in sorted(groups.items())}


def _thumbnail(roi, size: int = 256):
    image = getattr(roi, "image", None)
    if image is None:
        return None
    image = image.copy()
    image.thumbnail((size, size))
    return image


def evaluate_styles(
    style_engines: dict[str, tuple[Engine, Library]],
    queries: list[Query],
    base: Setting,
    opts: MetricOptions | None = None,
) -> dict[str, dict]:
    """Base-setting summary per prompt style (one onboarded store per style)."""
    out = {}
    for style, (engine, library) in style_engines.items():
        plan = SweepPlan(base=base)
        run = evaluate(engine, queries, library, plan, opts, sweeps=False)
        summ = run.results[run.plan.base].summary()
        summ["n_unresolved"] = len(run.unresolved)
        summ["n_failed"] = len(run.failed)
        out[style] = summ
    return out

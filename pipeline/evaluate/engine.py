"""The one place that talks to the query package: ROI + embedding once per (query, ROI variant), then
cheap re-rankings for every sweep setting (no model calls)."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from pipeline.evaluate.datasets import Query

#: A ranking long enough to hold every library mesh (metrics need the full list).
FULL_RANKING = 1_000_000


@dataclass(frozen=True)
class Setting:
    """The cheap knobs of one ranking: mode, stage-1 threshold, fallback top-k (and its unit), ROI variant."""

    mode: str = "two-stage"
    threshold: float | None = None  # None: the retriever's default (the paper's 0.37)
    fallback_k: int = 10
    roi: str = "segm"
    fallback_unit: str = "captions"  # what fallback_k counts: caption rows (paper) or meshes

    def label(self) -> str:
        tau = "default" if self.threshold is None else f"{self.threshold:.2f}"
        return f"{self.mode} tau={tau} k={self.fallback_k} {self.fallback_unit} roi={self.roi}"

    def to_json(self) -> dict:
        return {
            "mode": self.mode,
            "threshold": self.threshold,
            "fallback_k": self.fallback_k,
            "fallback_unit": self.fallback_unit,
            "roi": self.roi,
        }


@dataclass
class Ranked:
    """One ranking as plain data."""

    ids: list[str]
    scores: list  # the key the ranking is sorted by (a float, or (image, text) for two-stage): ties
    names: list[str]
    text_scores: list[float | None]
    image_scores: list[float | None]
    best_views: list[int | None]
    used_fallback: bool
    n_stage1: int | None
    decided_by: str | None
    seconds: float
    threshold: float | None = None  # the tau the retriever applied (its default when the setting has None)
    view_ids: np.ndarray | None = None  # mesh id of every ranked view, best first (paper metric set)
    view_keys: np.ndarray | None = None  # (n_views, 1 or 2) float sort keys of those views, for ties


@dataclass
class Embedded:
    """A query's ROI and embedding for one ROI variant."""

    roi: object  # pipeline.query Roi (has .image, a PIL image)
    embedding: object
    seconds: float


class Engine:
    """Holds a loaded :class:`pipeline.query.Retriever` for one store."""

    def __init__(self, retriever, store_path: str):
        self.retriever = retriever
        self.store_path = store_path

    @classmethod
    def open(
        cls,
        store_path: str,
        profile: str = "offline",
        model_overrides: dict | None = None,
        device: str | None = None,
        models: dict | None = None,
    ) -> Engine:
        from pipeline.query import Retriever

        r = Retriever.open(
            store_path, profile=profile, model_overrides=model_overrides or None, device=device, models=models
        )
        return cls(r, store_path)

    def embed(self, query: Query, roi_mode: str) -> Embedded:
        """ROI (from the query's mask for ``segm``, its box for ``bbox``; the detector when neither) + embedding."""
        from PIL import Image

        t0 = time.perf_counter()
        mask = query.mask if roi_mode == "segm" else None
        box = tuple(query.box) if query.box else None
        if box is None and mask is None and query.mask:
            with Image.open(query.mask) as m:  # bbox variant of a mask-only query: the mask's box
                box = _mask_box(np.asarray(m.convert("L")) > 0)
        roi = self.retriever.make_roi(query.image, query.prompt, box=box, mask=mask, roi_mode=roi_mode)
        emb = self.retriever.embed(roi, query.prompt)
        return Embedded(roi, emb, time.perf_counter() - t0)

    def rank(self, emb: Embedded, setting: Setting, views: bool = False) -> Ranked:
        """Every mesh the setting ranks; ``views`` adds the view-level ranking (the paper's mAP@k)."""
        t0 = time.perf_counter()
        res = self.retriever.rank(
            emb.embedding,
            mode=setting.mode,
            threshold=setting.threshold,
            fallback_k=setting.fallback_k,
            top=FULL_RANKING,
            fallback_unit=setting.fallback_unit,
            views=views,
        )
        seconds = time.perf_counter() - t0
        view_ids = view_keys = None
        vr = getattr(res, "view_ranking", None)
        if vr is not None:
            view_ids = self._mesh_ids()[vr.mesh_idx]
            cols = [vr.scores] if vr.tiebreak is None else [vr.scores, vr.tiebreak]
            view_keys = np.stack([np.asarray(c, np.float64) for c in cols], axis=1)
        cands = list(res.candidates)
        text = [_f(getattr(c, "text_score", None)) for c in cands]
        image = [_f(getattr(c, "image_score", None)) for c in cands]
        return Ranked(
            ids=[c.mesh_id for c in cands],
            scores=[_sort_key(setting.mode, t, i) for t, i in zip(text, image, strict=True)],
            names=[getattr(c, "name", None) or c.mesh_id for c in cands],
            text_scores=text,
            image_scores=image,
            best_views=[getattr(c, "best_view", None) for c in cands],
            used_fallback=bool(getattr(res, "used_fallback", False)),
            n_stage1=getattr(res, "n_stage1", None),
            decided_by=getattr(res, "decided_by", None),
            seconds=seconds,
            threshold=getattr(res, "threshold", setting.threshold),
            view_ids=view_ids,
            view_keys=view_keys,
        )

    def _mesh_ids(self) -> np.ndarray:
        """The retriever's active mesh ids as an object array (indexed by a view ranking's mesh_idx)."""
        if getattr(self, "_ids", None) is None:
            self._ids = np.asarray(list(self.retriever.mesh_ids), dtype=object)
        return self._ids


def _sort_key(mode: str, text: float | None, image: float | None):
    """What the mode sorts by (two-stage: image score, then text score), for judging ties."""
    nan = float("nan")
    t = nan if text is None else text
    i = nan if image is None else image
    return {"text-only": t, "image-only": i}.get(mode, (i, t))


def _f(x) -> float | None:
    return None if x is None else float(x)


def _mask_box(mask: np.ndarray) -> tuple[float, float, float, float] | None:
    ys, xs = np.nonzero(mask)
    if not len(xs):
        return None
    return float(xs.min()), float(ys.min()), float(xs.max() + 1), float(ys.max() + 1)

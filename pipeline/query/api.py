"""The Python API of the query path; the CLI is a thin wrapper around it.

>>> from pipeline.query import Retriever
>>> with Retriever.open("data/store", profile="offline") as r:
...     result = r.query("photo.jpg", "the yellow mustard bottle", box=(120, 40, 260, 300))
...     print(result.best.name)

``make_roi`` -> ``embed`` -> ``rank`` are the three steps of ``query``; ``rank`` calls no model, so sweeps
over tau, fallback-k, prompt weight or mode reuse one embedding.

A ``Retriever`` is thread-safe: stage 1 borrows a DuckDB connection per call, models are built once under a
lock, and the adapters and stage 2 only read shared state. It answers from the store state it opened;
:meth:`Retriever.reopened` gives one on the latest commits that shares the loaded models (what the HTTP
service does when :func:`pipeline.query.library.store_version` changes).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterable

import numpy as np

from pipeline.query.embed import embed_roi, stage1_vector, strategy_for
from pipeline.query.errors import QueryError
from pipeline.query.handoff import HandOff
from pipeline.query.images import clean_prompt, load_mask, load_photo, parse_box
from pipeline.query.library import StoreTables, check_models, latest_onboarding, store_version
from pipeline.query.results import Candidate, QueryEmbedding, QueryResult, ViewRanking
from pipeline.query.roi import Roi, make_roi
from pipeline.query.settings import MODES, QuerySettings, settings_for
from pipeline.query.stage1 import FALLBACK_UNITS, TextFilter
from pipeline.query.stage2 import ViewReranker
from pipeline.query.verify import LocalVerifier


class Retriever:
    """An opened store plus the profile's query models, loaded once. Use :meth:`open`."""

    def __init__(
        self, store, profile, tables: StoreTables, settings: QuerySettings, *, device, models, threads
    ):
        self.store = store
        self.profile = profile
        self.tables = tables
        self.settings = settings
        self.device = device
        self.strategy = strategy_for(profile.clip_image_encoder is not None)
        self.load_seconds: dict[str, float] = {}
        self._models: dict[str, object] = dict(models or {})
        self._model_lock = threading.Lock()
        # tables.con (candidate_views, mesh lookups) runs one statement at a time
        self._db_lock = threading.Lock()
        self.version = None  # store version this state was read at (set by open)
        self._open_args: dict = {}
        self.text_filter = TextFilter(tables.captions, threads)
        self.reranker = ViewReranker(tables.views, tables.meshes.num_rows, device)
        from pipeline.localfeat.config import VerifyConfig

        self.verifier = LocalVerifier(
            store,
            tables.onboarding,
            tables.meshes.column("mesh_id").to_pylist(),
            VerifyConfig(top=settings.verify_top, weight=settings.verify_weight),
        )
        m = tables.meshes
        self._mesh_id = m.column("mesh_id").to_pylist()
        self._name = m.column("name").to_pylist()
        self._path = m.column("source_path").to_pylist()
        self._root = m.column("library_root").to_pylist()
        render = tables.onboarding.render_config()
        self.handoff = HandOff(self.mesh, self.view_poses, render.up if render else "auto", self._mesh_id)

    # ------------------------------------------------------------------ opening
    @classmethod
    def open(
        cls,
        store_path,
        profile: str = "offline",
        model_overrides: dict[str, str] | None = None,
        device: str | None = None,
        models: dict[str, object] | None = None,
        *,
        settings: QuerySettings | None = None,
        use_cache: bool = True,
        threads: int | None = None,
        settings_changes: dict | None = None,
        preload: bool = True,
    ) -> Retriever:
        """Open ``store_path`` for queries with ``profile`` ("auto": the profile the store was onboarded with).

        ``models`` injects ready adapters by role (tests, notebooks); other roles are built through
        :func:`pipeline.models.registry.create_model` from the profile (detector and segmenter on first use).
        ``settings`` / ``settings_changes`` replace / adjust the profile's query defaults
        (:mod:`pipeline.query.settings`); ``use_cache`` reads and writes ``STORE/_cache/query``;
        ``preload=False`` defers every model to its first use.
        """
        from pipeline.profiles import PROFILES, get_profile
        from pipeline.store import Store

        version = store_version(store_path)  # read first: a commit racing the open is seen next time
        store = Store.open(store_path)
        try:
            onboarding = latest_onboarding(store)
            if profile in (None, "", "auto"):
                profile = onboarding.profile if onboarding.profile in PROFILES else "offline"
            try:
                prof = get_profile(profile, model_overrides)
            except ValueError as exc:
                raise QueryError(str(exc)) from None
            settings = (settings or settings_for(prof.name)).with_changes(**(settings_changes or {}))
            strategy = strategy_for(prof.clip_image_encoder is not None)
            # the caption and view spaces must match even for roles this query does not load
            roles = {*strategy.roles(settings.prompt_weight > 0), "text_encoder", "view_encoder"}
            check_models(onboarding, prof.name, {r: getattr(prof, r).key() for r in roles}, store.root)
            tables = StoreTables(store, onboarding, use_cache=use_cache)
            r = cls(store, prof, tables, settings, device=device, models=models, threads=threads)
            r.version = version
            r._open_args = {
                "store_path": store_path,
                "profile": prof.name,
                "model_overrides": model_overrides,
                "device": device,
                "settings": settings,
                "use_cache": use_cache,
                "threads": threads,
            }
            if preload:
                r.load_models(r.required_roles())
            return r
        except BaseException:
            store.close()
            raise

    def __enter__(self) -> Retriever:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def reopened(self, *, preload: bool = True) -> Retriever:
        """A new Retriever on the store's latest commits, with the same settings and the already loaded
        models (no model is loaded twice). This one stays usable until closed."""
        with self._model_lock:
            models = dict(self._models)
        r = Retriever.open(**self._open_args, models=models, preload=False)
        r.load_seconds = dict(self.load_seconds)
        if preload:
            r.load_models(r.required_roles())
        return r

    def is_stale(self) -> bool:
        """Whether the store has commits this Retriever does not see (cheap: for polling)."""
        return store_version(self.store.root) != self.version

    def close(self) -> None:
        self.text_filter.close()
        self.tables.con.close()
        self.store.close()

    # ------------------------------------------------------------------ models
    def required_roles(self, source: str | None = None, roi_mode: str = "segm") -> list[str]:
        """Roles a query needs: the embedding roles, plus what finds the object when it comes from
        ``source`` ("detector": detector and segmenter; "box": segmenter; "mask" or None: nothing more)."""
        roles = list(self.strategy.roles(self.settings.prompt_weight > 0))
        if source == "detector":
            roles.append("detector")
        if source in ("detector", "box") and roi_mode == "segm":
            roles.append("segmenter")
        return [r for r in roles if r in self._models or getattr(self.profile, r, None) is not None]

    def load_models(self, roles: Iterable[str]) -> None:
        """Build the adapters of ``roles`` now (not yet loaded ones only)."""
        for role in roles:
            self.model(role)

    def model(self, role: str):
        """The adapter of ``role`` (built on first use), or ``None`` when the profile has no such role."""
        if role in self._models:
            return self._models[role]
        spec = getattr(self.profile, role, None)
        if spec is None:
            return None
        from pipeline.models.registry import create_model

        with self._model_lock:  # concurrent first uses build the model once
            if role in self._models:
                return self._models[role]
            extra = {} if self.device in (None, "", "auto") else {"device": self.device}
            t0 = time.perf_counter()
            adapter = create_model(role, spec, **extra)
            self.load_seconds[role] = time.perf_counter() - t0
            self._models[role] = adapter
        return adapter

    # ------------------------------------------------------------------ steps
    def make_roi(self, image, prompt: str, box=None, mask=None, roi_mode: str = "segm") -> Roi:
        """Validate the inputs and cut the prompted object out of ``image`` (path, PIL image or array)."""
        s = self.settings
        prompt = clean_prompt(prompt, s.max_prompt_chars)
        photo = load_photo(image, max_side=s.max_side, min_side=s.min_side)
        box_v = parse_box(box) if box is not None else None
        mask_v = load_mask(mask, photo, s.min_roi_side) if mask is not None else None
        roi = make_roi(
            photo,
            prompt,
            box=box_v,
            mask=mask_v,
            roi_mode=roi_mode,
            model=self.model,
            background=s.background,
            min_side=s.min_roi_side,
            profile=self.profile.name,
            box_segmenter=s.box_segmenter,
        )
        roi.notes.extend([] if photo.scale == 1.0 else [f"image downscaled by {photo.scale:.3f}"])
        roi.photo_source, roi.photo_size = photo.source, photo.original_size
        return roi

    def embed(self, roi: Roi, prompt: str) -> QueryEmbedding:
        """The ROI's vectors in the caption space and the view-encoder space (plus the prompt's if used)."""
        prompt = clean_prompt(prompt, self.settings.max_prompt_chars)
        with_prompt = self.settings.prompt_weight > 0
        emb = embed_roi(self.strategy, self.model, roi, prompt, with_prompt)
        if self.settings.verify and self.verifier.available:
            emb.local = self.verifier.roi_features(roi.image, roi.crop_mask)
        return emb

    def _verified(self, emb: QueryEmbedding, mesh_idx, image, order, verify, timings):
        """Fuse local-feature inliers into the top ``verify_top`` of ``order``: (new order, fused, inliers)."""
        inl = np.full(len(mesh_idx), -1, np.int64)
        fused = np.asarray(image, np.float32).copy()
        on = self.settings.verify if verify is None else bool(verify)
        if not on or emb.local is None or not len(order):
            return order, fused, inl
        top = order[: max(int(self.settings.verify_top), 0)]
        cache, seconds = self.verifier.inliers(emb.local, [int(mesh_idx[j]) for j in top], emb.inliers)
        timings["verify_ms"] = seconds * 1000
        counts = np.array([cache[int(mesh_idx[j])][0] for j in top], np.int64)
        inl[top] = counts
        fused[top] += self.verifier.cfg.bonus(counts)
        rest = np.full(len(order), len(order), np.int64)
        rest[order] = np.arange(len(order))  # the global order breaks ties of the fused score
        return np.lexsort((rest, -fused)), fused, inl

    def rank(
        self,
        emb: QueryEmbedding,
        mode: str = "two-stage",
        threshold: float | None = None,
        fallback_k: int = 10,
        top: int = 5,
        prompt_weight: float | None = None,
        fallback_unit: str | None = None,
        views: bool = False,
        verify: bool | None = None,
    ) -> QueryResult:
        """Rank the store's models for ``emb`` (no model calls: cheap enough for parameter sweeps).

        ``fallback_unit``: what ``fallback_k`` counts when nothing passes tau, ``"captions"`` (the paper's:
        the top-k caption rows kept as their distinct models) or ``"meshes"``; ``None`` = the settings'.
        ``views`` also attaches the view-level ranking (:class:`ViewRanking`) that the paper's mAP@k uses
        (raw view scores: verification re-ranks models, not views).
        ``verify`` (default: the settings') re-ranks the top candidates with local features when the
        embedding carries the ROI's keypoints; inlier counts are cached on ``emb``.
        """
        if mode not in MODES:
            raise QueryError(f"unknown mode {mode!r}; choose from {', '.join(MODES)}")
        unit = self.settings.fallback_unit if fallback_unit is None else fallback_unit
        if unit not in FALLBACK_UNITS:
            raise QueryError(f"unknown fallback unit {unit!r}; choose from {', '.join(FALLBACK_UNITS)}")
        if int(top) < 1 or int(fallback_k) < 1:
            raise QueryError("--top and --fallback-k must be at least 1")
        tau = self.settings.threshold if threshold is None else float(threshold)
        w = self.settings.prompt_weight if prompt_weight is None else float(prompt_weight)
        if not 0.0 <= w <= 1.0:
            raise QueryError(f"prompt weight must be within [0, 1], got {w}")
        if w > 0 and emb.prompt_vec is None:
            raise QueryError(
                "this embedding has no prompt vector: open the Retriever with a prompt weight > 0"
            )
        timings: dict[str, float] = {}
        try:
            if mode == "image-only":
                result = self._rank_image_only(emb, top, tau, fallback_k, w, timings, unit, views, verify)
                self.handoff.fill(result.candidates)  # issue 19: the pose-estimator hand-off
                return result
            text_only = mode == "text-only"
            s1 = self.text_filter.run(
                stage1_vector(emb, w),
                None if text_only else tau,
                top if text_only else fallback_k,
                "meshes" if text_only else unit,  # text-only lists the top models
            )
            s2 = self.reranker.score(emb.image_space, s1.mesh_idx, per_view=views and not text_only)
        except ValueError as exc:  # vector widths that do not match the store
            raise QueryError(
                f"{exc}: the store was embedded with other models than this query uses"
            ) from None
        timings["stage1_ms"] = s1.seconds * 1000
        timings["stage2_ms"] = s2.seconds * 1000
        fused, inl = s2.scores, np.full(len(s1.mesh_idx), -1, np.int64)
        if mode == "text-only":
            order = np.arange(len(s1.mesh_idx))
            decided, used_fallback = "stage1", False
        else:
            order = np.lexsort((s1.mesh_idx, -s1.scores, -s2.scores))
            order, fused, inl = self._verified(emb, s1.mesh_idx, s2.scores, order, verify, timings)
            decided, used_fallback = ("stage1" if len(order) == 1 else "stage2"), s1.used_fallback
        order = order[: int(top)]
        cands = [
            self._candidate(
                i + 1, s1.mesh_idx[j], s1.scores[j], s2.scores[j], s2.best_view[j], inl[j], fused[j]
            )
            for i, j in enumerate(order)
        ]
        result = QueryResult(
            cands, used_fallback, decided, len(s1.mesh_idx), timings, mode, tau, int(fallback_k), w, unit
        )
        if views and mode == "text-only":
            result.view_ranking = self._caption_ranking(stage1_vector(emb, w), s1.mesh_idx)
        elif views:
            result.view_ranking = _view_ranking(s1.mesh_idx, s2, s1.scores)
        self.handoff.fill(result.candidates)  # issue 19: the pose-estimator hand-off
        return result

    def _caption_ranking(self, vec, mesh_idx: np.ndarray) -> ViewRanking:
        """Every caption row of ``mesh_idx`` by its own stage-1 cosine (text-only's view-level ranking)."""
        rows_mesh, scores = self.text_filter.caption_scores(vec)
        keep = np.zeros(self.n_meshes, bool)
        keep[np.asarray(mesh_idx, dtype=np.int64)] = True
        sel = keep[rows_mesh]
        m, s = rows_mesh[sel], scores[sel]
        order = np.lexsort((m, -s))
        return ViewRanking(m[order], np.full(len(order), -1, np.int16), s[order])

    def _rank_image_only(
        self, emb, top, tau, fallback_k, w, timings, unit, views=False, verify=None
    ) -> QueryResult:
        s2 = self.reranker.score(emb.image_space, None, per_view=views)
        timings["stage1_ms"] = 0.0
        timings["stage2_ms"] = s2.seconds * 1000
        idx = np.arange(len(s2.scores))
        order = np.lexsort((idx, -s2.scores))
        order, fused, inl = self._verified(emb, idx, s2.scores, order, verify, timings)
        order = order[: int(top)]
        cands = [
            self._candidate(i + 1, j, None, s2.scores[j], s2.best_view[j], inl[j], fused[j])
            for i, j in enumerate(order)
        ]
        result = QueryResult(
            cands, False, "stage2", len(idx), timings, "image-only", tau, int(fallback_k), w, unit
        )
        if views:
            result.view_ranking = _view_ranking(idx, s2, None)
        return result

    def _candidate(self, rank, mesh_idx, text, image, view, inliers=-1, fused=None) -> Candidate:
        j = int(mesh_idx)
        ok = image is not None and np.isfinite(image)
        verified = ok and inliers is not None and inliers >= 0
        return Candidate(
            rank=rank,
            mesh_id=self._mesh_id[j],
            name=self._name[j],
            source_path=self._path[j],
            text_score=None if text is None else round(float(text), 6),
            image_score=round(float(image), 6) if ok else None,
            best_view=int(view) if ok and view >= 0 else None,
            library_root=self._root[j],
            inliers=int(inliers) if verified else None,
            score=round(float(fused), 6) if verified and fused is not None else None,
        )

    def query(
        self,
        image,
        prompt: str,
        box=None,
        mask=None,
        roi_mode: str = "segm",
        mode: str = "two-stage",
        threshold: float | None = None,
        fallback_k: int = 10,
        top: int = 5,
        prompt_weight: float | None = None,
        fallback_unit: str | None = None,
        verify: bool | None = None,
    ) -> QueryResult:
        """ROI, embedding and ranking of one photo + prompt, with a per-step latency breakdown."""
        if mode not in MODES:
            raise QueryError(f"unknown mode {mode!r}; choose from {', '.join(MODES)}")
        loaded = sum(self.load_seconds.values())
        t0 = time.perf_counter()
        roi = self.make_roi(image, prompt, box=box, mask=mask, roi_mode=roi_mode)
        t1 = time.perf_counter()
        load_roi = sum(self.load_seconds.values()) - loaded
        emb = self.embed(roi, prompt)
        t2 = time.perf_counter()
        load_emb = sum(self.load_seconds.values()) - loaded - load_roi
        result = self.rank(emb, mode, threshold, fallback_k, top, prompt_weight, fallback_unit, verify=verify)
        t3 = time.perf_counter()
        result.timings = {
            "model_load_ms": (load_roi + load_emb) * 1000,
            "roi_ms": (t1 - t0 - load_roi) * 1000,
            "embed_ms": (t2 - t1 - load_emb) * 1000,
            **result.timings,
            "total_ms": (t3 - t0) * 1000,
        }
        result.query = {
            "image": roi.photo_source,
            "image_size": list(roi.photo_size),
            "prompt": clean_prompt(prompt, self.settings.max_prompt_chars),
            "profile": self.profile.name,
            "roi": roi.describe(),
            "embedding": emb.describe(),
        }
        result.roi = roi  # for --explain; not serialised
        return result

    # ------------------------------------------------------------------ store lookups
    @property
    def n_meshes(self) -> int:
        return len(self._mesh_id)

    @property
    def mesh_ids(self) -> list[str]:
        """Active mesh ids in ``mesh_idx`` order (what a :class:`ViewRanking`'s ``mesh_idx`` indexes)."""
        return self._mesh_id

    def mesh(self, mesh_id: str) -> dict:
        """The active-mesh record of ``mesh_id`` (name, paths, format, referenced files)."""
        if not hasattr(self, "_row_of"):
            self._row_of = {m: j for j, m in enumerate(self._mesh_id)}
        j = self._row_of.get(mesh_id)
        if j is None:
            raise QueryError(f"no active mesh {mesh_id!r} in this store")
        return self.tables.meshes.slice(j, 1).to_pylist()[0]

    def view_poses(self, mesh_ids: list[str]) -> list[dict]:
        """Cameras (pose, field of view, size; no pixels) of the rendered views of ``mesh_ids``."""
        from pipeline.db import load_sql

        fp = self.tables.onboarding.fingerprints.get("render")
        params = {"mesh_ids": list(mesh_ids), "render_fingerprint": fp}
        with self._db_lock:
            return self.tables.con.sql(load_sql("view_poses"), params=params).to_arrow_table().to_pylist()

    def candidate_views(self, mesh_ids: list[str]) -> list[dict]:
        """Rendered views (PNG bytes) and captions of ``mesh_ids`` (``sql/candidate_views.sql``)."""
        from pipeline.db import load_sql

        fps = self.tables.onboarding.fingerprints
        params = {
            "mesh_ids": list(mesh_ids),
            "render_fingerprint": fps["render"],
            "caption_fingerprint": fps["caption"],
        }
        with self._db_lock:
            rel = self.tables.con.sql(load_sql("candidate_views"), params=params)
            return rel.to_arrow_table().to_pylist()


def _view_ranking(mesh_idx: np.ndarray, s2, text: np.ndarray | None) -> ViewRanking:
    """Flatten stage 2's per-view matrix of ``mesh_idx`` into one ranking of views, best first."""
    scores, ids = s2.view_scores, s2.view_ids
    mesh = np.broadcast_to(np.asarray(mesh_idx, dtype=np.int32)[:, None], scores.shape)
    valid = ids >= 0
    m, v, s = mesh[valid], ids[valid], scores[valid]
    t = None if text is None else np.broadcast_to(np.asarray(text, np.float32)[:, None], scores.shape)[valid]
    keys = (v, m, -s) if t is None else (v, m, -t, -s)
    order = np.lexsort(keys)
    return ViewRanking(m[order], v[order], s[order], None if t is None else t[order])

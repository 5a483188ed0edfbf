"""The ranking state that every step takes and returns, the request it answers, and the read-only context.

* :class:`RankRequest`: the knobs of one ranking (mode, tau, fallback k and unit, top, prompt weight,
  verification, view-level output), validated once.
* :class:`RankContext`: what the steps read and never change: the stage-1 text filter, the stage-2 view
  reranker, the local-feature verifier, the active meshes' columns, the query settings, the open-set
  calibration and the pose-estimator hand-off.
* :class:`RankState`: the candidates (positions in the store's active meshes), their scores per channel, the
  best view per channel, the current order, and what the result reports (fallback, deciding stage, notes,
  timings, view-level ranking). Arrays in ``scores`` and ``best_view`` are aligned with ``mesh_idx``; a new
  step adds its own channel (a learned image score, a confidence) instead of a new field.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pipeline.query.errors import QueryError
from pipeline.query.results import Candidate, QueryEmbedding, QueryResult, ViewRanking
from pipeline.query.stage1 import FALLBACK_UNITS


@dataclass(frozen=True)
class RankRequest:
    """The knobs of one ranking, resolved against the settings (:meth:`make` validates them)."""

    mode: str
    threshold: float
    fallback_k: int
    top: int
    prompt_weight: float
    fallback_unit: str
    views: bool = False
    verify: bool = False
    accept_threshold: float | None = None  # open-set operating point (None: the calibration's)

    @classmethod
    def make(
        cls,
        settings,
        emb: QueryEmbedding,
        modes,
        mode: str | None = None,
        threshold: float | None = None,
        fallback_k: int = 10,
        top: int = 5,
        prompt_weight: float | None = None,
        fallback_unit: str | None = None,
        views: bool = False,
        verify: bool | None = None,
        accept_threshold: float | None = None,
    ) -> RankRequest:
        """The request for ``emb`` (``None`` = the settings' value); a bad knob is a :class:`QueryError`."""
        mode = settings.mode if mode is None else mode
        if mode not in modes:
            raise QueryError(f"unknown mode {mode!r}; choose from {', '.join(modes)}")
        unit = settings.fallback_unit if fallback_unit is None else fallback_unit
        if unit not in FALLBACK_UNITS:
            raise QueryError(f"unknown fallback unit {unit!r}; choose from {', '.join(FALLBACK_UNITS)}")
        if int(top) < 1 or int(fallback_k) < 1:
            raise QueryError("--top and --fallback-k must be at least 1")
        tau = settings.threshold if threshold is None else float(threshold)
        w = settings.prompt_weight if prompt_weight is None else float(prompt_weight)
        if not 0.0 <= w <= 1.0:
            raise QueryError(f"prompt weight must be within [0, 1], got {w}")
        if w > 0 and emb.prompt_vec is None:
            raise QueryError(
                "this embedding has no prompt vector: open the Retriever with a prompt weight > 0"
            )
        on = settings.verify if verify is None else bool(verify)
        accept = getattr(settings, "accept_threshold", None) if accept_threshold is None else accept_threshold
        if accept is not None and not 0.0 <= float(accept) <= 1.0:
            raise QueryError(f"accept threshold must be within [0, 1], got {accept}")
        accept = None if accept is None else float(accept)
        return cls(mode, tau, int(fallback_k), int(top), w, unit, bool(views), on, accept)


@dataclass
class RankContext:
    """The store side every step reads: stage-1 filter, stage-2 reranker, verifier, mesh columns, settings."""

    text_filter: Any  # pipeline.query.stage1.TextFilter
    reranker: Any  # pipeline.query.stage2.ViewReranker
    verifier: Any  # pipeline.query.verify.LocalVerifier
    settings: Any  # pipeline.query.settings.QuerySettings
    mesh_id: list[str]
    name: list[str]
    source_path: list[str]
    library_root: list[str | None]
    calibration: Any = None  # pipeline.query.accept.Calibration of the open-set verdict (None: none)
    calibration_mismatch: str | None = None  # why the calibration does not apply to this store
    learned: Any = None  # pipeline.query.stage2.ViewReranker over the learned encoder's views, if any
    handoff: Any = None  # pipeline.query.handoff.HandOff: the candidates' pose-estimator fields (None: none)
    adapter: Any = None  # pipeline.adapter.table.Adapter fitted on this store state (None: none)
    adapter_note: str | None = None  # why the store's adapter is not used (it was fitted on other models)
    patches: Any = None  # pipeline.query.patches.PatchMatcher of the verdict (None: no learned encoder)

    @classmethod
    def from_meshes(cls, meshes, **parts) -> RankContext:
        """The context over the active-meshes table ``meshes`` (row j = ``mesh_idx`` j)."""
        return cls(
            **parts,
            mesh_id=meshes.column("mesh_id").to_pylist(),
            name=meshes.column("name").to_pylist(),
            source_path=meshes.column("source_path").to_pylist(),
            library_root=meshes.column("library_root").to_pylist(),
        )

    @property
    def n_meshes(self) -> int:
        return len(self.mesh_id)

    def accept_model(self, variant: str):
        """The calibration's acceptance model of ranking ``variant`` (``None``: no calibration or none for
        it)."""
        return self.calibration.variants.get(variant) if self.calibration is not None else None


@dataclass
class RankState:
    """One ranking in progress: what each step reads and adds to."""

    ctx: RankContext
    emb: QueryEmbedding
    request: RankRequest
    mesh_idx: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))  # the candidates
    every_mesh: bool = False  # the candidates are every active mesh in store order
    scores: dict[str, np.ndarray] = field(default_factory=dict)  # channel -> score per candidate
    best_view: dict[str, np.ndarray] = field(default_factory=dict)  # channel -> view_index per candidate
    per_view: dict[str, Any] = field(default_factory=dict)  # channel -> per-view scores (Stage2Result)
    order: np.ndarray | None = None  # positions into mesh_idx, best first
    used_fallback: bool = False
    decided_by: str | None = None
    candidates: list[Candidate] = field(default_factory=list)  # the ranked records (top of ``order``)
    view_ranking: ViewRanking | None = None
    verdict: Any = None  # pipeline.query.accept.Verdict (the acceptance step)
    patch_prefetch: Any = None  # (mesh position, Future) of the top-1's view tokens (steps/patch_prefetch.py)
    notes: list[str] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)  # milliseconds per step

    def result(self) -> QueryResult:
        """The finished ranking as the query path's result record."""
        r = self.request
        out = QueryResult(
            self.candidates,
            self.used_fallback,
            self.decided_by,
            len(self.mesh_idx),
            self.timings,
            r.mode,
            r.threshold,
            r.fallback_k,
            r.prompt_weight,
            r.fallback_unit,
        )
        out.view_ranking = self.view_ranking
        out.notes = list(self.notes)
        out.verdict = self.verdict
        out.fused = "learned" in self.scores
        out.adapted = "learned_adapted" in self.scores
        return out


def model_mismatch(exc: ValueError) -> QueryError:
    """A vector width that does not match the store, as the query path's error."""
    return QueryError(f"{exc}: the store was embedded with other models than this query uses")

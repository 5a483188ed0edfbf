"""Plain result records of the query path (JSON-ready, no model or store handles)."""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field

import numpy as np


@dataclass
class QueryEmbedding:
    """The ROI's vectors: everything :meth:`Retriever.rank` needs, so ranking never calls a model."""

    text_space: np.ndarray  # float32, caption-embedding space (CLIP image of the ROI / MiniLM of its caption)
    image_space: np.ndarray  # float32, view-encoder space (DINOv2 / descriptor of the ROI)
    prompt_vec: np.ndarray | None = None  # float32, the prompt in caption-embedding space (when used)
    roi_caption: str | None = None  # the ROI's own caption (caption-space profiles)
    local: object | None = None  # the ROI's local features (pipeline.localfeat.Features) when verifying
    inliers: dict = field(default_factory=dict)  # mesh_idx -> (inliers, best view): verification cache
    learned: np.ndarray | None = (
        None  # float32, the ROI in the learned encoder's space (when the store has it)
    )
    #: float16 (k, hidden): the learned encoder's tokens of the ROI's object patches (the open-set verdict's
    #: patch agreement, pipeline.query.patches; None without the learned encoder)
    learned_patches: np.ndarray | None = None

    def describe(self) -> dict:
        return {
            "text_dim": int(self.text_space.shape[-1]),
            "image_dim": int(self.image_space.shape[-1]),
            "prompt_used": self.prompt_vec is not None,
            "roi_caption": self.roi_caption,
            "roi_keypoints": None if self.local is None else len(self.local),
            "learned_dim": None if self.learned is None else int(self.learned.shape[-1]),
            "learned_patches": None if self.learned_patches is None else len(self.learned_patches),
        }


@dataclass
class Candidate:
    """One ranked model."""

    rank: int
    mesh_id: str
    name: str
    source_path: str
    text_score: float | None  # stage-1 score (max over the model's captions)
    image_score: float | None  # stage-2 score (max over the model's views)
    best_view: int | None  # view_index of the best-matching view
    library_root: str | None = None
    inliers: int | None = None  # RANSAC inliers of the best-verified view (None: not verified)
    #: the fused score the candidates are ranked by (pipeline.query.fusion: learned and descriptor cosines,
    #: text score, verification bonus); None when nothing was fused (image_score applies)
    score: float | None = None
    learned_score: float | None = None  # learned-encoder cosine (max over the model's views)
    # hand-off to a pose estimator (pipeline.query.handoff; docs/query.md): None when not known
    units_guess: str | None = None  # units of the source file: "m" | "mm"
    units_from: str | None = None  # "gltf" (the format says metres) | "extent" (a guess from the size)
    scale_to_metres: float | None = None  # file coordinates * this = metres
    extent_m: list[float] | None = None  # axis-aligned size (x, y, z) of the source mesh in metres
    best_view_pose: list[list[float]] | None = (
        None  # 4x4: source frame in metres -> best view's camera (OpenCV)
    )
    intrinsics: dict | None = None  # {"K": 3x3, "width", "height"} of the best view

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class ViewRanking:
    """Every ranked reference view (or, in text-only mode, caption row) with its mesh, best first.

    The unit the paper's mAP@k ranks (``pipeline.evaluate.metrics``, the ``paper`` set): two-stage ranks the
    stage-1 candidates' views by their stage-2 cosine (then the mesh's stage-1 score), image-only every view,
    text-only every caption row of the ranked meshes by its own stage-1 cosine.
    """

    mesh_idx: np.ndarray  # int32 position in the store's active meshes, per item
    view_index: np.ndarray  # int16 view_index per item (-1 for a caption row)
    scores: np.ndarray  # float32, the primary sort key
    tiebreak: np.ndarray | None = None  # float32 secondary key (two-stage: the mesh's stage-1 score)


@dataclass
class QueryResult:
    """Ranked candidates plus how they were decided."""

    candidates: list[Candidate]
    used_fallback: bool
    decided_by: str  # "stage1" | "stage2"
    n_stage1: int  # models kept by stage 1 (all models in image-only mode)
    timings: dict[str, float] = field(default_factory=dict)  # milliseconds per step
    mode: str = "two-stage"
    threshold: float | None = None
    fallback_k: int = 10
    prompt_weight: float = 0.0
    fallback_unit: str = "captions"  # what fallback_k counted: caption rows or meshes
    query: dict = field(default_factory=dict)  # image, prompt, ROI and models (filled by Retriever.query)
    roi: object | None = field(default=None, repr=False)  # the Roi (Retriever.query), not serialised
    view_ranking: ViewRanking | None = field(default=None, repr=False)  # rank(views=True); not serialised
    notes: list[str] = field(default_factory=list)  # e.g. why stage 1 used the exact path
    verdict: object | None = None  # pipeline.query.accept.Verdict: the open-set decision (set by rank)
    fused: bool = False  # ranked by the fused learned / descriptor / text score (pipeline.query.fusion)
    adapted: bool = False  # the learned cosine went through the store's query adapter (pipeline.adapter)

    @property
    def best(self) -> Candidate | None:
        return self.candidates[0] if self.candidates else None

    @property
    def accepted(self) -> bool | None:
        """Whether the best candidate matches the object (``None``: not judged, see ``acceptance.note``)."""
        return None if self.verdict is None else self.verdict.accepted

    @property
    def confidence(self) -> float | None:
        """Calibrated probability that the best candidate is the right model (``None``: not judged)."""
        return None if self.verdict is None else self.verdict.confidence

    @property
    def accept_threshold(self) -> float | None:
        return None if self.verdict is None else self.verdict.threshold

    def to_dict(self) -> dict:
        out = {
            "query": self.query,
            "accepted": self.accepted,
            "confidence": self.confidence,
            "accept_threshold": self.accept_threshold,
            "acceptance": None if self.verdict is None else self.verdict.to_dict(),
            "mode": self.mode,
            "decided_by": self.decided_by,
            "used_fallback": self.used_fallback,
            "threshold": self.threshold,
            "fallback_k": self.fallback_k,
            "fallback_unit": self.fallback_unit,
            "prompt_weight": self.prompt_weight,
            "n_stage1": self.n_stage1,
            "fused": self.fused,
            "adapted": self.adapted,
            "candidates": [c.to_dict() for c in self.candidates],
            "timings_ms": {k: round(v, 3) for k, v in self.timings.items()},
        }
        if self.notes:
            out["notes"] = list(self.notes)
        return _finite(out)

    def to_json(self, indent: int | None = None) -> str:
        return json.dumps(self.to_dict(), indent=indent)


def _finite(obj):
    """JSON has no inf/NaN: they become null."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj

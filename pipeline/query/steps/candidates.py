"""The top ``top`` of the order as :class:`~pipeline.query.results.Candidate` records (rounded scores)."""

from __future__ import annotations

import numpy as np

from pipeline.query.results import Candidate
from pipeline.query.steps.state import RankContext, RankState


def run(state: RankState) -> RankState:
    """Candidate records of the best ``request.top`` candidates, rank 1 first."""
    text = state.scores.get("text")
    image, view = state.scores["image"], state.best_view["image"]
    inliers, fused = state.scores.get("inliers"), state.scores.get("fused")
    state.candidates = [
        candidate(
            state.ctx,
            i + 1,
            state.mesh_idx[j],
            None if text is None else text[j],
            image[j],
            view[j],
            -1 if inliers is None else inliers[j],
            None if fused is None else fused[j],
        )
        for i, j in enumerate(state.order[: state.request.top])
    ]
    return state


def candidate(ctx: RankContext, rank, mesh_idx, text, image, view, inliers=-1, fused=None) -> Candidate:
    """One record: scores of a mesh without views are ``None``; ``score`` only for verified candidates."""
    j = int(mesh_idx)
    ok = image is not None and np.isfinite(image)
    verified = ok and inliers is not None and inliers >= 0
    return Candidate(
        rank=rank,
        mesh_id=ctx.mesh_id[j],
        name=ctx.name[j],
        source_path=ctx.source_path[j],
        text_score=None if text is None else round(float(text), 6),
        image_score=round(float(image), 6) if ok else None,
        best_view=int(view) if ok and view >= 0 else None,
        library_root=ctx.library_root[j],
        inliers=int(inliers) if verified else None,
        score=round(float(fused), 6) if verified and fused is not None else None,
    )

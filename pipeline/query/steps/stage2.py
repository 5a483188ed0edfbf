"""Stage 2: the ROI's view-encoder vector against every candidate's views (the ``image`` channel)."""

from __future__ import annotations

from pipeline.query.steps.state import RankState, model_mismatch


def run(state: RankState, *, per_view: bool = True) -> RankState:
    """Max-over-views cosine and best view per candidate; with ``per_view`` and a view-level request, also
    every view's score (what :mod:`pipeline.query.steps.view_ranking` flattens)."""
    which = None if state.every_mesh else state.mesh_idx  # None: every view scored once, then gathered
    try:
        s2 = state.ctx.reranker.score(state.emb.image_space, which, per_view=per_view and state.request.views)
    except ValueError as exc:  # vector widths that do not match the store
        raise model_mismatch(exc) from None
    state.scores["image"], state.best_view["image"] = s2.scores, s2.best_view
    state.per_view["image"] = s2
    state.timings["stage2_ms"] = s2.seconds * 1000
    return state

"""Stage 1 of two-stage: the models whose captions pass tau, or the fallback top-k when none does."""

from __future__ import annotations

import numpy as np

from pipeline.query.embed import stage1_vector
from pipeline.query.steps.state import RankState, model_mismatch


def run(state: RankState) -> RankState:
    """Candidates = the stage-1 shortlist in its own order, with their text scores."""
    r = state.request
    try:
        s1 = state.ctx.text_filter.run(
            stage1_vector(state.emb, r.prompt_weight), r.threshold, r.fallback_k, r.fallback_unit
        )
    except ValueError as exc:  # vector widths that do not match the store
        raise model_mismatch(exc) from None
    state.mesh_idx, state.scores["text"] = s1.mesh_idx, s1.scores
    state.order = np.arange(len(s1.mesh_idx))
    state.used_fallback, state.decided_by = s1.used_fallback, "stage1"
    state.timings["stage1_ms"] = s1.seconds * 1000
    return state

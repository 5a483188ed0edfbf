"""Stage 1 of text-only: the ``top`` models by their best caption score (no tau, no fallback)."""

from __future__ import annotations

import numpy as np

from pipeline.query.embed import stage1_vector
from pipeline.query.steps.state import RankState, model_mismatch


def run(state: RankState) -> RankState:
    """Candidates = the top models by stage-1 score, best first; stage 1 decides the order."""
    r = state.request
    try:
        s1 = state.ctx.text_filter.run(stage1_vector(state.emb, r.prompt_weight), None, r.top, "meshes")
    except ValueError as exc:
        raise model_mismatch(exc) from None
    state.mesh_idx, state.scores["text"] = s1.mesh_idx, s1.scores
    state.order = np.arange(len(s1.mesh_idx))
    state.decided_by = "stage1"
    state.timings["stage1_ms"] = s1.seconds * 1000
    return state

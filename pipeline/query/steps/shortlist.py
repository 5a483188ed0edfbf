"""Stage 1 of two-stage: the models whose captions pass tau, or the fallback top-k when none does."""

from __future__ import annotations

import numpy as np

from pipeline.query.embed import stage1_vector
from pipeline.query.fusion import fusing
from pipeline.query.steps.state import RankState, model_mismatch


def run(state: RankState) -> RankState:
    """Candidates = the stage-1 shortlist in its own order, with their text scores. When the learned encoder
    is fused and ``fuse_all`` is set, every model is a candidate: the text score is a term of the fused
    score instead of a cut at tau (no fallback); only up to ``fuse_all_max_models`` models, past which the
    shortlist is cut at tau as without fusion (stage 1 is then what keeps a query's cost bounded)."""
    r, s = state.request, state.ctx.settings
    every = fusing(state) and s.fuse_all and state.ctx.n_meshes <= s.fuse_all_max_models
    try:
        s1 = state.ctx.text_filter.run(
            stage1_vector(state.emb, r.prompt_weight),
            None if every else r.threshold,
            state.ctx.n_meshes if every else r.fallback_k,
            "meshes" if every else r.fallback_unit,
        )
    except ValueError as exc:  # vector widths that do not match the store
        raise model_mismatch(exc) from None
    state.mesh_idx, state.scores["text"] = s1.mesh_idx, s1.scores
    state.order = np.arange(len(s1.mesh_idx))
    state.used_fallback, state.decided_by = s1.used_fallback and not every, "stage1"
    state.timings["stage1_ms"] = s1.seconds * 1000
    state.notes.extend(getattr(state.ctx.text_filter, "notes", ()))  # e.g. the index fell back to exact
    return state

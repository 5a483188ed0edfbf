"""Text-only's view-level ranking: every caption row of the candidates by its own stage-1 cosine, on request."""

from __future__ import annotations

import numpy as np

from pipeline.query.embed import stage1_vector
from pipeline.query.results import ViewRanking
from pipeline.query.steps.state import RankState


def run(state: RankState) -> RankState:
    """Attach the caption-level :class:`ViewRanking` when the request has ``views``."""
    if not state.request.views:
        return state
    vec = stage1_vector(state.emb, state.request.prompt_weight)
    rows_mesh, scores = state.ctx.text_filter.caption_scores(vec)
    keep = np.zeros(state.ctx.n_meshes, bool)
    keep[np.asarray(state.mesh_idx, dtype=np.int64)] = True
    sel = keep[rows_mesh]
    m, s = rows_mesh[sel], scores[sel]
    order = np.lexsort((m, -s))
    state.view_ranking = ViewRanking(m[order], np.full(len(order), -1, np.int16), s[order])
    return state

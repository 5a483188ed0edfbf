"""The view-level ranking (the paper's mAP@k unit) of stage 2's per-view scores, on request.

Every view of every candidate, best first by its own cosine, then by the mesh's stage-1 score when there is
one (two-stage); raw view scores: verification re-ranks models, not views.
"""

from __future__ import annotations

import numpy as np

from pipeline.query.results import ViewRanking
from pipeline.query.steps.state import RankState


def run(state: RankState) -> RankState:
    """Attach :class:`ViewRanking` when the request has ``views``."""
    if state.request.views:
        state.view_ranking = flatten(state.mesh_idx, state.per_view["image"], state.scores.get("text"))
    return state


def flatten(mesh_idx: np.ndarray, s2, text: np.ndarray | None) -> ViewRanking:
    """Flatten stage 2's per-view matrix of ``mesh_idx`` into one ranking of views, best first."""
    scores, ids = s2.view_scores, s2.view_ids
    mesh = np.broadcast_to(np.asarray(mesh_idx, dtype=np.int32)[:, None], scores.shape)
    valid = ids >= 0
    m, v, s = mesh[valid], ids[valid], scores[valid]
    t = None if text is None else np.broadcast_to(np.asarray(text, np.float32)[:, None], scores.shape)[valid]
    keys = (v, m, -s) if t is None else (v, m, -t, -s)
    order = np.lexsort(keys)
    return ViewRanking(m[order], v[order], s[order], None if t is None else t[order])

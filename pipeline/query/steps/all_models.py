"""Stage 1 of image-only: every active model is a candidate (no text score)."""

from __future__ import annotations

import numpy as np

from pipeline.query.steps.state import RankState


def run(state: RankState) -> RankState:
    """Candidates = all active meshes in store order."""
    state.mesh_idx = np.arange(state.ctx.n_meshes)
    state.order = np.arange(state.ctx.n_meshes)
    state.every_mesh = True
    state.timings["stage1_ms"] = 0.0
    return state

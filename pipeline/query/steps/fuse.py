"""Fusion: order the candidates by their score channels, best first (ties: the next channel, then store order)."""

from __future__ import annotations

import numpy as np

from pipeline.query.steps.state import RankState


def run(state: RankState, *, by: tuple[str, ...]) -> RankState:
    """Sort by the channels ``by`` (descending, the first one primary); stage 2 decides the order unless
    stage 1 left a single candidate."""
    keys = (state.mesh_idx, *(-state.scores[c] for c in reversed(by)))
    state.order = np.lexsort(keys)
    if state.decided_by is None or len(state.order) != 1:
        state.decided_by = "stage2"
    return state

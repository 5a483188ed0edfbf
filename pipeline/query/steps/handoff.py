"""The pose-estimator hand-off of the result records: units, scale, metric size, best-view pose and
intrinsics (:class:`pipeline.query.handoff.HandOff`; docs/query.md, "Hand-off to a pose estimator").

Runs after ``candidates`` (it fills their records in place) and changes no score or order.
"""

from __future__ import annotations

from pipeline.query.steps.state import RankState


def run(state: RankState) -> RankState:
    """Fill the candidates' hand-off fields (nothing when the context has no hand-off)."""
    if state.ctx.handoff is not None:
        state.ctx.handoff.fill(state.candidates)
    return state

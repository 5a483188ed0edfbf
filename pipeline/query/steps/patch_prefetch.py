"""Start the open-set verdict's patch agreement early: encode the current top-1's views beside verification.

The acceptance step compares the ROI's patch tokens with those of the top-1's two best stored views (every
view where the calibration reads :data:`pipeline.query.patches.UNION_FEATURES`), one
encoder pass (torch) that used to wait for verification (OpenCV), which ran before it. Both release the GIL,
so where torch leaves a core free (:func:`pipeline.query.overlap.overlapping`) this step starts that pass
for the model that leads before verification, in the shared side pool, and verification runs meanwhile.
When verification keeps that model first (most queries), the acceptance step finds its views' tokens
ready (:meth:`pipeline.query.patches.PatchMatcher.view_tokens` caches them); when it crowns another, the
acceptance step encodes that one's views as before and the early pass only warmed the cache. Nothing runs
when the verdict will not read patch features, when there is nothing to verify, or without a free side
thread (a free core, no other query's side call in it): run in place, the pass would only come sooner,
and for nothing when the top-1 changes.

With the tokens onboarding stores (``view_patches``, :mod:`pipeline.onboard.stages.patches`) the early
work is one store read of the model's two rows instead of an encoder pass; the step is kept for stores
without them.
"""

from __future__ import annotations

from pipeline.query.accept import variant_of
from pipeline.query.overlap import beside_if_free, overlapping
from pipeline.query.patches import best_views
from pipeline.query.steps.state import RankState


def run(state: RankState) -> RankState:
    """Start the encoder pass over the current top-1's patch views (``state.patch_prefetch``)."""
    ctx, emb, order = state.ctx, state.emb, state.order
    if ctx.patches is None or emb.learned is None or emb.learned_patches is None or order is None:
        return state
    if not len(order) or not state.request.verify or emb.local is None or not overlapping():
        return state
    model = ctx.accept_model(variant_of(state.request.mode, True))
    if not ctx.patches.wanted(model):
        return state
    position = int(order[0])
    mesh = int(state.mesh_idx[position])
    mesh_id = ctx.mesh_id[mesh]
    views = best_views(ctx.learned, emb.learned, mesh, k=ctx.patches.views_read(model))  # all, for the union
    if views:  # only where a side thread is free: run in place, the pass would be wasted if the top-1 changes
        started = beside_if_free(lambda: ctx.patches.view_tokens(mesh_id, views))
        if started is not None:
            state.patch_prefetch = (position, started)
    return state

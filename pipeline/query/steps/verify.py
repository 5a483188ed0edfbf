"""Verification: local-feature inliers of the top ``verify_top`` candidates, fused into their image score.

Adds the ``inliers`` channel (-1: not verified) and the ``fused`` channel (image score plus the inlier bonus,
:meth:`pipeline.localfeat.config.VerifyConfig.bonus`) and re-orders by it; the previous order breaks ties.
Inlier counts are cached on the embedding, so re-rankings verify each (query, model) pair once.
"""

from __future__ import annotations

import numpy as np

from pipeline.query.fusion import fusing
from pipeline.query.steps.state import RankState


def run(state: RankState, *, base: str = "image") -> RankState:
    """Verify and re-rank when the request asks for it and the embedding carries the ROI's keypoints; the
    inlier bonus is added to the ``base`` channel (the fused score when the learned encoder takes part, with
    the weight ``fuse_verify_weight`` instead of ``verify_weight``). With the query adapter (a ``BASE_plain``
    channel beside ``base``) the ranking's ``fused`` gets ``adapter_fuse_verify_weight`` and ``fused_plain``
    the plain bonus, for the open-set verdict."""
    emb, ctx, order = state.emb, state.ctx, state.order
    inl = np.full(len(state.mesh_idx), -1, np.int64)
    fused = np.asarray(state.scores[base], np.float32).copy()
    state.scores["inliers"], state.scores["fused"] = inl, fused
    plain = state.scores.get(f"{base}_plain")  # the query adapter's ranking: the plain score beside it
    if plain is not None:
        plain = state.scores["fused_plain"] = np.asarray(plain, np.float32).copy()
    if not state.request.verify or emb.local is None or not len(order):
        return state
    top = order[: max(int(ctx.settings.verify_top), 0)]
    cache, seconds = ctx.verifier.inliers(emb.local, [int(state.mesh_idx[j]) for j in top], emb.inliers)
    state.timings["verify_ms"] = seconds * 1000
    counts = np.array([cache[int(state.mesh_idx[j])][0] for j in top], np.int64)
    inl[top] = counts
    weight = ctx.settings.fuse_verify_weight if fusing(state) else None
    if plain is not None:
        plain[top] += ctx.verifier.cfg.bonus(counts, weight)
        weight = ctx.settings.adapter_fuse_verify_weight
    fused[top] += ctx.verifier.cfg.bonus(counts, weight)
    rest = np.full(len(order), len(order), np.int64)
    rest[order] = np.arange(len(order))  # the previous order breaks ties of the fused score
    state.order = np.lexsort((rest, -fused))
    return state

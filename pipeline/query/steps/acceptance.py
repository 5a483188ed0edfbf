"""The open-set verdict: is the best candidate the object, or does the library not hold it?

Reads the ranking as the earlier steps left it (the order, before it is cut to ``top``; the ranking key:
``fused`` when verification ran, else ``image``, and ``text`` in text-only mode; ``inliers``; the stage-1
``text`` channel; ``used_fallback``; the ``learned`` channel when fusing) plus the query's image and learned
scores over the library's cohort, and sets
``state.verdict`` (``accepted``, ``confidence``) with :func:`pipeline.query.accept.judge`.
"""

from __future__ import annotations

import time

import numpy as np

from pipeline.query.accept import cohort_indices, cohort_stats, judge, ranking_features, variant_of
from pipeline.query.patches import VIEWS, best_views, runner_up_lead, union_agreement
from pipeline.query.steps.state import RankState


def run(state: RankState, *, key: str = "fused") -> RankState:
    """Judge the ranking; ``key``: the channel the order was decided by (``fused`` falls back to ``image``)."""
    ctx, order = state.ctx, state.order
    if order is None:
        order = np.arange(len(state.mesh_idx))
    # with the query adapter the verdict reads the plain scores its calibration was fitted on (the adapter
    # pulls an absent object's ROI towards the library's models too): docs/results.md, section 11
    keys = state.scores.get(f"{key}_plain", state.scores.get(key, state.scores.get("image")))
    inliers = state.scores.get("inliers")
    if inliers is None:
        inliers = np.full(len(state.mesh_idx), -1, np.int64)
    verified = bool(len(order)) and int(inliers[int(order[0])]) >= 0
    cohort = learned_cohort = None
    learned = state.scores.get("learned")
    members = cohort_indices(ctx.n_meshes)
    samples = {"candidates": int(np.isfinite(np.asarray(keys, np.float64)).sum()), "cohort": len(members)}
    if len(order):
        cohort = cohort_stats(ctx.reranker.score(state.emb.image_space, members).scores)
        if learned is not None:
            learned_cohort = cohort_stats(ctx.learned.score(state.emb.learned, members).scores)
    feats = ranking_features(
        order,
        keys,
        inliers,
        state.scores.get("text"),
        state.used_fallback,
        state.scores.get("image"),
        cohort,
        learned,
        learned_cohort,
    )
    variant = variant_of(state.request.mode, verified)
    model = ctx.accept_model(variant)
    if ctx.patches is not None and len(order) and state.emb.learned is not None and ctx.patches.wanted(model):
        # patch agreement of the ROI and the top-1's views that the plain learned cosine ranks first
        t0 = time.perf_counter()
        early = state.patch_prefetch
        if early is not None and early[0] == int(order[0]):  # started beside verification: its tokens
            early[1].result()  # are then in the view cache (raises what the encoder raised)
        mesh = int(state.mesh_idx[int(order[0])])  # its views best first: two, or all for the union
        ranked = best_views(ctx.learned, state.emb.learned, mesh, k=ctx.patches.views_read(model))
        top = ctx.patches.features(state.emb.learned_patches, ctx.mesh_id[mesh], ranked[:VIEWS])
        feats.update(top)
        if len(order) > 1 and ctx.patches.wanted_runner_up(model):  # and the runner-up's, for its lead
            feats.update(runner_up_lead(top, _patches(state, int(order[1]))))
        if ctx.patches.wanted_union(model):  # and against every view of the top-1 at once
            tokens = ctx.patches.view_tokens(ctx.mesh_id[mesh], ranked)
            feats.update(union_agreement(state.emb.learned_patches, tokens, top.get("patch_cover")))
        state.timings["patches_ms"] = (time.perf_counter() - t0) * 1000
    threshold = state.request.accept_threshold
    state.verdict = judge(ctx.calibration, feats, variant, threshold, ctx.calibration_mismatch, samples)
    return state


def _patches(state: RankState, position: int) -> dict[str, float | None]:
    """The patch agreement of the ROI with the candidate at ``position``: its views that the plain learned
    cosine ranks first (:func:`pipeline.query.patches.best_views`)."""
    ctx = state.ctx
    mesh = int(state.mesh_idx[position])
    views = best_views(ctx.learned, state.emb.learned, mesh)
    return ctx.patches.features(state.emb.learned_patches, ctx.mesh_id[mesh], views)

"""The fused score's two text terms: the ROI caption's and the prompt's own cosine with each candidate's
closest caption (``text_roi`` and ``text_prompt`` channels, :mod:`pipeline.query.fusion`).

Stage 1's ``text`` score is the best caption's weighted mean of the two cosines; the fusion weighs them apart
(fitted so, docs/results.md section 7.2). Computed only when the learned encoder is fused over a library of
at most ``fuse_all_max_models`` models (two matrix-vector products over its captions); past that, or without
a prompt (or with prompt weight 0), the fusion falls back as :func:`pipeline.query.fusion.fuse` says.
"""

from __future__ import annotations

import time

import numpy as np

from pipeline.query.fusion import fusing
from pipeline.query.steps.state import RankState, model_mismatch


def best_per_model(text_filter, vec: np.ndarray, n_meshes: int) -> np.ndarray:
    """Max cosine of ``vec`` over each model's captions, by store position (-1 for a model without any)."""
    best = np.full(n_meshes, -1.0, np.float32)
    models, scores = text_filter.model_scores(vec)
    best[models] = scores
    return best


def run(state: RankState) -> RankState:
    """Add ``text_roi`` (and ``text_prompt`` when the request uses the prompt) for every candidate."""
    ctx, emb = state.ctx, state.emb
    if not fusing(state) or ctx.n_meshes > ctx.settings.fuse_all_max_models or not len(state.mesh_idx):
        return state
    t0 = time.perf_counter()
    try:
        roi = best_per_model(ctx.text_filter, emb.text_space, ctx.n_meshes)
        state.scores["text_roi"] = roi[state.mesh_idx]
        if emb.prompt_vec is not None and state.request.prompt_weight > 0:
            prompt = best_per_model(ctx.text_filter, emb.prompt_vec, ctx.n_meshes)
            state.scores["text_prompt"] = prompt[state.mesh_idx]
    except ValueError as exc:  # vector widths that do not match the store
        raise model_mismatch(exc) from None
    state.timings["text_terms_ms"] = (time.perf_counter() - t0) * 1000
    return state

"""The learned view encoder's step: its cosine per candidate (``learned`` channel) and the ``fusion`` channel
that the order and verification use (:mod:`pipeline.query.fusion`).

Without learned embeddings (a store onboarded before the encoder existed, ``--model learned_encoder=none``)
``fusion`` is the stage-2 ``image`` score itself, so the ranking is exactly the descriptor's, as before.
"""

from __future__ import annotations

import numpy as np

from pipeline.query.errors import QueryError
from pipeline.query.fusion import FusionWeights, fuse, fusing
from pipeline.query.steps.state import RankState, model_mismatch


def run(state: RankState) -> RankState:
    """Add the ``learned`` and ``fusion`` channels (``fusion`` = ``image`` when not fusing)."""
    image = np.asarray(state.scores["image"], np.float32)
    if not fusing(state):
        state.scores["fusion"] = image
        return state
    which = None if state.every_mesh else state.mesh_idx
    try:
        s = state.ctx.learned.score(state.emb.learned, which)
    except ValueError as exc:  # vector widths that do not match the store
        raise model_mismatch(exc) from None
    try:
        weights = FusionWeights.of(state.ctx.settings)
    except ValueError as exc:
        raise QueryError(str(exc)) from None
    state.scores["learned"], state.best_view["learned"] = s.scores, s.best_view
    text, prompt = state.scores.get("text_roi"), state.scores.get("text_prompt")
    if text is None:  # the text terms were not computed: stage 1's blended score takes both weights
        text = state.scores.get("text")
    state.scores["fusion"] = fuse(s.scores, image, text, weights, prompt)
    state.timings["learned_ms"] = s.seconds * 1000
    return state

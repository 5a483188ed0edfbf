"""The learned view encoder's step: its cosine per candidate (``learned`` channel) and the ``fusion`` channel
that the order and verification use (:mod:`pipeline.query.fusion`).

Without learned embeddings (a store onboarded before the encoder existed, ``--model learned_encoder=none``)
``fusion`` is the stage-2 ``image`` score itself, so the ranking is exactly the descriptor's, as before.

With the store's query adapter (:mod:`pipeline.adapter`; the ``adapter`` setting) the ranking's ``fusion``
fuses the adapted cosine (``learned_adapted``) with the ``adapter_fuse_*`` weights, while ``learned`` and
``fusion_plain`` keep the plain cosine and the plain weights: the open-set verdict reads those, as its
calibration was fitted on them.
"""

from __future__ import annotations

import numpy as np

from pipeline.query.errors import QueryError
from pipeline.query.fusion import FusionWeights, fuse, fusing
from pipeline.query.steps.state import RankState, model_mismatch


def run(state: RankState) -> RankState:
    """Add the ``learned`` and ``fusion`` channels (``fusion`` = ``image`` when not fusing), and with an
    adapter ``learned_adapted`` and ``fusion_plain``."""
    image = np.asarray(state.scores["image"], np.float32)
    if not fusing(state):
        state.scores["fusion"] = image
        return state
    ctx = state.ctx
    which = None if state.every_mesh else state.mesh_idx
    adapter = ctx.adapter if ctx.settings.adapter else None
    try:
        s = ctx.learned.score(state.emb.learned, which)
        a = None
        if adapter is not None:
            from pipeline.adapter.fit import apply_adapter

            a = ctx.learned.score(apply_adapter(state.emb.learned, adapter.matrix), which)
    except ValueError as exc:  # vector widths that do not match the store
        raise model_mismatch(exc) from None
    try:
        weights = FusionWeights.of(ctx.settings)
        adapted_weights = FusionWeights.of(ctx.settings, adapted=True) if a is not None else None
    except ValueError as exc:
        raise QueryError(str(exc)) from None
    state.scores["learned"], state.best_view["learned"] = s.scores, s.best_view
    text, prompt = state.scores.get("text_roi"), state.scores.get("text_prompt")
    if text is None:  # the text terms were not computed: stage 1's blended score takes both weights
        text = state.scores.get("text")
    state.scores["fusion"] = fuse(s.scores, image, text, weights, prompt)
    state.timings["learned_ms"] = s.seconds * 1000
    if a is not None:
        state.scores["learned_adapted"], state.best_view["learned"] = a.scores, a.best_view
        state.scores["fusion_plain"] = state.scores["fusion"]
        state.scores["fusion"] = fuse(a.scores, image, text, adapted_weights, prompt)
        state.timings["learned_ms"] += a.seconds * 1000
    elif ctx.settings.adapter and ctx.adapter_note:
        state.notes.append(ctx.adapter_note)
    return state

"""Ranking steps, and :data:`STEP_LISTS`: the one declaration of which steps each mode runs, in order.

A ranking is a list of steps over one :class:`~pipeline.query.steps.state.RankState`: each step is the
``run(state, **options) -> state`` of its own module in this folder, reads what earlier steps left (the
candidates, their score channels, best views, order) and adds its own. The modes (``two-stage``,
``text-only``, ``image-only``; the ``mode`` setting or the request's) are step lists, not branches:
:func:`rank` looks the list up and runs it. ``Retriever.rank``, and through it the CLI, batch mode, the
service and the evaluation sweeps, all rank here; no step calls a model, so re-rankings are cheap.

================  =====================================================================================
``shortlist``     stage 1 (two-stage): captions passing tau, else the fallback top-k (``text`` channel)
``top_text``      stage 1 (text-only): the ``top`` models by caption score
``all_models``    stage 1 (image-only): every active model
``stage2``        view-encoder scores and best views (``image`` channel, per-view scores)
``text_terms``    the ROI caption's and the prompt's own text scores for the fusion (``text_roi``, ``text_prompt``)
``learned``       the learned view encoder's cosine (``learned``) and the fused score (``fusion``)
``fuse``          order by score channels
``patch_prefetch``  the verdict's encoder pass over the top-1's views, started beside verification
``verify``        local-feature inliers of the top candidates fused into their score (``inliers``, ``fused``)
``acceptance``    the open-set verdict: calibrated ``confidence`` and ``accepted`` (pipeline.query.accept)
``candidates``    the top of the order as result records
``handoff``       the records' pose-estimator fields: units, metric size, best-view pose (pipeline.query.handoff)
``view_ranking``  the view-level ranking of stage 2 (paper mAP@k), on request
``caption_ranking``  text-only's caption-level ranking, on request
================  =====================================================================================
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from pipeline.query.results import QueryEmbedding, QueryResult
from pipeline.query.steps import (
    acceptance,
    all_models,
    candidates,
    caption_ranking,
    fuse,
    handoff,
    learned,
    patch_prefetch,
    shortlist,
    stage2,
    text_terms,
    top_text,
    verify,
    view_ranking,
)
from pipeline.query.steps.state import RankContext, RankRequest, RankState


@dataclass(frozen=True)
class Step:
    """One entry of a step list: a step module's ``run`` and the options it is called with."""

    run: Callable[..., RankState]
    options: dict = field(default_factory=dict)

    def __call__(self, state: RankState) -> RankState:
        return self.run(state, **self.options)


#: mode -> its steps, in order (the ``mode`` setting chooses; pipeline.query.modes.MODES names the same keys)
STEP_LISTS: dict[str, tuple[Step, ...]] = {
    "two-stage": (
        Step(shortlist.run),
        Step(stage2.run),
        Step(text_terms.run),
        Step(learned.run),
        Step(fuse.run, {"by": ("fusion", "text")}),
        Step(patch_prefetch.run),
        Step(verify.run, {"base": "fusion"}),
        Step(acceptance.run),
        Step(candidates.run),
        Step(handoff.run),
        Step(view_ranking.run),
    ),
    "text-only": (
        Step(top_text.run),
        Step(stage2.run, {"per_view": False}),
        Step(acceptance.run, {"key": "text"}),
        Step(candidates.run),
        Step(handoff.run),
        Step(caption_ranking.run),
    ),
    "image-only": (
        Step(all_models.run),
        Step(stage2.run),
        Step(learned.run),
        Step(fuse.run, {"by": ("fusion",)}),
        Step(patch_prefetch.run),
        Step(verify.run, {"base": "fusion"}),
        Step(acceptance.run),
        Step(candidates.run),
        Step(handoff.run),
        Step(view_ranking.run),
    ),
}


def run_steps(steps: tuple[Step, ...], state: RankState) -> RankState:
    """Run ``steps`` over ``state`` in order."""
    for step in steps:
        state = step(state)
    return state


def rank(ctx: RankContext, emb: QueryEmbedding, **knobs) -> QueryResult:
    """Rank the store's models for ``emb`` with the step list of the request's mode (``knobs``: see
    :meth:`RankRequest.make`)."""
    request = RankRequest.make(ctx.settings, emb, STEP_LISTS, **knobs)
    return run_steps(STEP_LISTS[request.mode], RankState(ctx, emb, request)).result()

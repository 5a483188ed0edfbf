"""What an opened store hands the ranking steps: its engines and the open-set calibration, built once.

:func:`ranking_context` builds, for one store state, the stage-1 filter (exact scan or the vector index,
``--stage1``), the stage-2 rerankers (the view encoder's and, where the store has its embeddings, the learned
encoder's), local-feature verification, the pose-estimator hand-off and the acceptance calibration, and
returns them in one :class:`~pipeline.query.steps.state.RankContext` (the steps read nothing else).
"""

from __future__ import annotations

from pipeline.query.errors import QueryError
from pipeline.query.handoff import HandOff
from pipeline.query.stage2 import ViewReranker
from pipeline.query.steps.state import RankContext
from pipeline.query.verify import LocalVerifier


def ranking_context(store, profile, tables, settings, *, device, threads) -> RankContext:
    """The :class:`RankContext` of one opened store state (``tables``: :class:`StoreTables`)."""
    from pipeline.index.choose import open_stage1
    from pipeline.localfeat.config import VerifyConfig

    try:
        text_filter = open_stage1(store, tables, settings.stage1, threads)
    except ValueError as exc:
        raise QueryError(str(exc)) from None
    n = tables.meshes.num_rows
    learned = tables.learned_views if profile.learned_encoder is not None else None
    mesh_ids = tables.meshes.column("mesh_id").to_pylist()
    cfg = VerifyConfig(top=settings.verify_top, weight=settings.verify_weight)
    render = tables.onboarding.render_config()
    check_background(settings, render, store.root)
    # the hand-off reads the tables directly, not through the Retriever's recovering view_poses (a query
    # already holds the recovery gate)
    handoff = HandOff(tables.mesh, tables.view_poses, render.up if render else "auto", mesh_ids)
    ctx = RankContext.from_meshes(
        tables.meshes,
        text_filter=text_filter,
        reranker=ViewReranker(tables.views, n, device),
        learned=None if learned is None else ViewReranker(learned, n, device),
        verifier=LocalVerifier(store, tables.onboarding, mesh_ids, cfg),
        handoff=handoff,
        settings=settings,
        adapter=None if learned is None else tables.adapter,
        adapter_note=None if learned is None else tables.adapter_note,
    )
    ctx.calibration, ctx.calibration_mismatch = calibration_for(
        profile, settings, tables.onboarding, fused=learned is not None
    )
    return ctx


def check_background(settings, render, store_root) -> None:
    """Refuse a query ``background`` other than the store's render background: the ROI is pasted on it,
    and the view encoders (the descriptor, the learned encoder's exposure step) take every pixel off the
    views' background for the object, so another colour would count the whole ROI as object. A store whose
    run did not record its render config is not checked."""
    if render is None:
        return
    want, got = tuple(int(c) for c in render.background), tuple(int(c) for c in settings.background)
    if want != got:
        raise QueryError(
            f"query background {got} differs from the background {want} that store {store_root} was rendered "
            f"on: leave the query setting background at {want}"
        )


def calibration_for(profile, settings, onboarding, *, fused: bool):
    """The profile's acceptance calibration (:mod:`pipeline.query.accept`) and why it does not fit this
    store and ranking (``None`` when it does; ``fused``: the learned encoder takes part)."""
    from pipeline.query.accept import CalibrationError, load_calibration, model_identities

    try:
        calibration = load_calibration(profile.name, settings.accept_model)
    except CalibrationError as exc:
        raise QueryError(str(exc)) from None
    if calibration is None:
        return None, None
    return calibration, calibration.mismatch(model_identities(profile, onboarding, fused, settings))

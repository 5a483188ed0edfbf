"""Opening a store for queries: the leased, consistent snapshot, the profile and the model check.

:func:`open_state` is what :meth:`pipeline.query.api.Retriever.open` does before it builds anything: read the
store version, take a reader lease (:mod:`pipeline.leases`), pin one consistent snapshot of every table
(:mod:`pipeline.snapshot`), resolve the profile and settings, and refuse a store whose caption, view or
learned embeddings come from other models than the query's. On any failure the snapshot and the lease are
released.
"""

from __future__ import annotations

from dataclasses import dataclass

from pipeline.query.embed import strategy_for
from pipeline.query.library import (
    StoreTables,
    check_learned,
    check_models,
    latest_onboarding,
    query_profile,
    store_version,
)
from pipeline.query.settings import QuerySettings, settings_for


@dataclass
class OpenedState:
    """A store state ready for a Retriever: close ``store`` and release ``lease`` when done."""

    store: object
    profile: object
    tables: StoreTables
    settings: QuerySettings
    version: object
    lease: object | None


def open_state(
    store_path, profile, model_overrides, *, settings, settings_changes, use_cache, lease
) -> OpenedState:
    """Open ``store_path`` (see :meth:`Retriever.open` for the arguments)."""
    from pipeline.leases import Lease
    from pipeline.snapshot import open_snapshot

    version = store_version(store_path)  # read first: a commit racing the open is seen next time
    held = Lease(store_path, "retriever") if lease else None
    try:
        store = open_snapshot(store_path, held)
    except BaseException:
        if held is not None:
            held.release()
        raise
    try:
        onboarding = latest_onboarding(store)
        prof = query_profile(onboarding, profile, model_overrides)
        settings = (settings or settings_for(prof.name)).with_changes(**(settings_changes or {}))
        strategy = strategy_for(prof.clip_image_encoder is not None)
        # the caption and view spaces must match even for roles this query does not load
        roles = {*strategy.roles(settings.prompt_weight > 0), "text_encoder", "view_encoder"}
        check_models(onboarding, prof.name, {r: getattr(prof, r).key() for r in roles}, store.root)
        check_learned(onboarding, prof.learned_encoder, store.root)
        tables = StoreTables(store, onboarding, use_cache=use_cache)
        return OpenedState(store, prof, tables, settings, version, held)
    except BaseException:
        store.close()
        if held is not None:
            held.release()
        raise

"""The open-set split without a second store: a :class:`~pipeline.query.Retriever` over a store's tables
with some meshes taken out, exactly as if the store had been onboarded without them.

Onboarding is per mesh (a mesh's renders, captions, embeddings and keypoints do not depend on the other
meshes), and the query path sees a store only through its active-mesh table (sorted by mesh_id, position =
``mesh_idx``), the caption and view embedding tables keyed by ``mesh_idx``, and the verifier's mesh-id list.
Dropping the rows of the removed meshes and renumbering ``mesh_idx`` in the same order therefore gives
stage 1 (tau, the caption fallback and its tie-break by ``mesh_idx``), stage 2 and verification the same
inputs as a store without those meshes; ``tests/test_openset.py`` checks this against a store built
without them. The store's query adapter, fitted on every model, is refitted on the models left
(:func:`pipeline.adapter.table.refit_for`), as an onboarding of the smaller library would have.
"""

from __future__ import annotations

import copy

import numpy as np
import pyarrow as pa


def _renumbered(table: pa.Table, keep: np.ndarray, new_idx: np.ndarray) -> pa.Table:
    """Rows of ``table`` whose ``mesh_idx`` is kept, with ``mesh_idx`` renumbered (order and metadata kept)."""
    if not table.num_rows:
        return table
    col = table.column("mesh_idx")
    idx = col.to_numpy().astype(np.int64)
    sel = keep[idx]
    out = table.filter(pa.array(sel))
    pos = out.schema.get_field_index("mesh_idx")
    renum = pa.array(new_idx[idx[sel]].astype(np.int64)).cast(col.type)
    out = out.set_column(pos, out.schema.field(pos), renum)
    return pa.Table.from_batches(out.to_batches(max_chunksize=65536), schema=out.schema)


def without_meshes(retriever, mesh_ids) -> object:
    """A Retriever like ``retriever`` (same store state, settings and loaded models) whose store lacks
    ``mesh_ids``. It shares the store handle and connection: close only the original."""
    from pipeline.query.api import Retriever

    drop = set(mesh_ids)
    tables = retriever.tables
    ids = tables.meshes.column("mesh_id").to_pylist()
    keep = np.array([m not in drop for m in ids], bool)
    if keep.all():
        raise ValueError("none of the meshes to leave out is in the store")
    if not keep.any():
        raise ValueError("leaving these meshes out would leave the store empty")
    new_idx = np.cumsum(keep) - 1
    sub = copy.copy(tables)
    meshes = tables.meshes.filter(pa.array(keep))
    if "mesh_idx" in meshes.column_names:
        pos = meshes.schema.get_field_index("mesh_idx")
        col = pa.array(np.arange(meshes.num_rows)).cast(meshes.schema.field(pos).type)
        meshes = meshes.set_column(pos, meshes.schema.field(pos), col)
    sub.meshes = meshes
    sub.captions = _renumbered(tables.captions, keep, new_idx)
    sub.views = _renumbered(tables.views, keep, new_idx)
    learned = getattr(tables, "learned_views", None)  # the learned view encoder's table, where the store has it
    sub.learned_views = None if learned is None else _renumbered(learned, keep, new_idx)
    if getattr(tables, "adapter", None) is not None:  # the query adapter such a store would have fitted
        from pipeline.adapter.table import refit_for

        sub.adapter = refit_for(sub, tables.adapter)
    models = {role: retriever.model(role) for role in retriever.required_roles()}
    r = Retriever(
        retriever.store,
        retriever.profile,
        sub,
        retriever.settings,
        device=retriever.device,
        models=models,
        threads=retriever.text_filter.threads,
    )
    r.version = retriever.version
    if getattr(retriever.ranking, "patches", None) is not None:  # views are keyed by mesh id: share the cache
        r.ranking.patches = retriever.ranking.patches
    r.recover = False  # a reload would bring the left-out meshes back: fail instead
    return r


def mesh_ids_with_labels(library, labels) -> list[str]:
    """Mesh ids of ``library`` (:class:`~pipeline.evaluate.library.Library`) whose class label is in ``labels``."""
    wanted = set(labels)
    return sorted(k for k, v in library.labels.items() if v in wanted)

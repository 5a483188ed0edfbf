"""The ``patches`` stage: the learned view encoder's object patch tokens of every view, for the open-set
verdict's patch agreement (:mod:`pipeline.query.patches`).

Without them the query encodes the top-1's two best views from their PNGs on every uncached query, the
largest part of a warm masked query on 2 cores (docs/performance.md, "Stored patch tokens"). The tokens
come from the forward pass that embeds the views (the ``embed_image`` stage of the same batch keeps them,
:func:`pipeline.onboard.stages.decoded.remember`; the Ray engine runs both steps in one actor,
:func:`pipeline.onboard.engines.ray_workers.step_groups`); only views that pass did not see (a store
onboarded before this stage existed) are encoded here.

Stored as float16 (what the query's token cache holds): the patches that hold the object, ``n_patches`` x
``dim``, each row L2-normalised; about 1.1 MB per model of 12 views at 224 px (84 MB for the 78 YCB
models, docs/performance.md, "Stored patch tokens").
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from pipeline import schemas
from pipeline.fingerprint import fingerprint
from pipeline.onboard.stages.base import ModelStage, error_row, with_errors

#: what the stored tokens are: bump when the patch selection or the encoding of the bytes changes
FORMAT = "object-patches-float16-v1"


def memo_kind(spec) -> str:
    """The batch memo's name for one learned encoder's object patch tokens (the same model key and options
    give the same tokens)."""
    return f"object-patches:{spec.key()}:{fingerprint(spec.options)}"


def settings() -> dict:
    """What decides which patches are kept and how (the stage's fingerprint reads it)."""
    from pipeline.query import patches

    return {
        "format": FORMAT,
        "tolerance": patches.TOLERANCE,
        "min_cover": patches.MIN_COVER,
        "min_patches": patches.MIN_PATCHES,
    }


class PatchStage(ModelStage):
    """Object patch tokens of every view, from the batch memo or one encoder pass over the rest."""

    def output_schema(self) -> pa.Schema:
        return with_errors(schemas.VIEW_PATCHES)

    def __call__(self, views: pa.Table) -> pa.Table:
        from pipeline.onboard.stages import decoded
        from pipeline.query import patches

        out = self.output_schema()
        extra = {"encoder_id": self.spec.key(), "fingerprint": self.fingerprint, "run_id": self.run_id}
        meta = views.select(["mesh_id", "view_index", "fingerprint"]).to_pylist()
        pngs = views.column("image").to_pylist()
        try:
            kind = memo_kind(self.spec)
            tokens = [None if b is None else decoded.recall(kind, b) for b in pngs]
            todo = [i for i, (b, t) in enumerate(zip(pngs, tokens, strict=True)) if b is not None and t is None]
            if todo:
                got = self.model.object_patches_batch([decoded.decoded_view(pngs[i]) for i in todo])
                for i, t in zip(todo, got, strict=True):
                    tokens[i] = t
            rows = []
            for m, t in zip(meta, tokens, strict=True):
                t = None if t is None else np.asarray(t, np.float16)
                rows.append(
                    {
                        "mesh_id": m["mesh_id"],
                        "view_index": m["view_index"],
                        "source_fingerprint": m["fingerprint"],
                        **extra,
                        "n_patches": 0 if t is None else t.shape[0],
                        "dim": 0 if t is None else t.shape[1],
                        "tokens": None if t is None else patches.tokens_bytes(t),
                    }
                )
        except Exception as exc:  # the batch's meshes become errors rows; the run goes on
            rows = [error_row(out, {**extra, "mesh_id": m}, exc) for m in dict.fromkeys(x["mesh_id"] for x in meta)]
        return pa.Table.from_pylist(rows, schema=out)

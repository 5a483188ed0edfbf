"""Probe stage: views in, the learned encoder's vectors of probe queries made from them out
(:mod:`pipeline.adapter.probes`; table ``probe_embeddings``, one row per probe, keyed by its source view)."""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from pipeline import schemas
from pipeline.models.protocols import l2_normalise
from pipeline.onboard.stages.base import ModelStage, error_row, with_errors


class ProbeStage(ModelStage):
    """Makes ``cfg.probes.per_mesh`` probe ROIs per mesh from its views and embeds them as query ROIs."""

    def __call__(self, views: pa.Table) -> pa.Table:
        from pipeline.adapter.probes import chosen_views, probe_roi
        from pipeline.onboard.stages.decoded import decoded_view

        out = with_errors(schemas.embedding_schema(self.model.dim))  # a model that cannot load ends the run
        cfg, background = self.cfg.probes, tuple(self.cfg.render.background)
        extra = {"encoder_id": self.spec.key(), "fingerprint": self.fingerprint, "run_id": self.run_id}
        by_mesh: dict[str, list[dict]] = {}
        for row in views.select(["mesh_id", "view_index", "image", "fingerprint"]).to_pylist():
            by_mesh.setdefault(row["mesh_id"], []).append(row)
        meta, rois, rows = [], [], []
        for mesh_id, mesh_views in by_mesh.items():
            at = {int(v["view_index"]): v for v in mesh_views}
            made = 0
            try:
                for vi in chosen_views(mesh_id, list(at), cfg):
                    image = np.asarray(decoded_view(at[vi]["image"]), dtype=np.uint8)
                    roi = probe_roi(image, mesh_id, vi, cfg, background)
                    if roi is not None:
                        meta.append(
                            {
                                "mesh_id": mesh_id,
                                "view_index": vi,
                                "source_fingerprint": at[vi]["fingerprint"],
                            }
                        )
                        rois.append(roi)
                        made += 1
                if not made:
                    raise ValueError("no view shows the object: no probe could be made")
            except Exception as exc:  # one mesh's failure is its errors row; the batch goes on
                del meta[len(meta) - made :], rois[len(rois) - made :]
                rows.append(error_row(out, {**extra, "mesh_id": mesh_id}, exc))
        if rois:
            enc = self.model
            try:
                vecs = l2_normalise(
                    np.asarray(getattr(enc, "encode_roi", enc.encode_image)(rois), np.float32)
                )
                if vecs.shape != (len(meta), enc.dim):
                    raise ValueError(
                        f"encoder returned shape {vecs.shape}, expected ({len(meta)}, {enc.dim})"
                    )
                rows += [
                    {**m, **extra, "dim": enc.dim, "embedding": v.tolist()}
                    for m, v in zip(meta, vecs, strict=True)
                ]
            except Exception as exc:  # the batch's meshes become errors rows; the run goes on
                rows += [
                    error_row(out, {**extra, "mesh_id": m}, exc)
                    for m in dict.fromkeys(x["mesh_id"] for x in meta)
                ]
        return pa.Table.from_pylist(rows, schema=out)

"""Embedding stages: captions -> text embeddings, views -> image embeddings (L2-normalised, float32)."""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from pipeline import schemas
from pipeline.models.protocols import l2_normalise
from pipeline.onboard.stages.base import ModelStage, error_row, with_errors


class EmbedStage(ModelStage):
    """Shared body: one encoder (built lazily, once), one fingerprint, rows keyed by the source rows."""

    @property
    def encoder_id(self) -> str:
        return self.spec.key()

    def output_schema(self) -> pa.Schema:
        return with_errors(schemas.embedding_schema(self.model.dim))

    def _encode(self, source: pa.Table):
        raise NotImplementedError

    def __call__(self, source: pa.Table) -> pa.Table:
        out = self.output_schema()  # builds the model: a model that cannot load ends the run
        meta = [
            {"mesh_id": m["mesh_id"], "view_index": m["view_index"], "source_fingerprint": m["fingerprint"]}
            for m in source.select(["mesh_id", "view_index", "fingerprint"]).to_pylist()
        ]
        extra = {"encoder_id": self.encoder_id, "fingerprint": self.fingerprint, "run_id": self.run_id}
        try:
            vecs = l2_normalise(self._encode(source))
            if vecs.shape != (len(meta), self.model.dim):
                raise ValueError(
                    f"encoder returned shape {vecs.shape}, expected ({len(meta)}, {self.model.dim})"
                )
            rows = [
                {**m, **extra, "dim": self.model.dim, "embedding": v.tolist()}
                for m, v in zip(meta, vecs, strict=True)
            ]
        except Exception as exc:  # the batch's meshes become errors rows; the run goes on
            rows = [
                error_row(out, {**extra, "mesh_id": m}, exc)
                for m in dict.fromkeys(x["mesh_id"] for x in meta)
            ]
        return pa.Table.from_pylist(rows, schema=out)


class TextEmbedStage(EmbedStage):
    """Embeds every caption with the profile's text encoder."""

    def _encode(self, captions: pa.Table):
        # template captions repeat across a mesh's views (936 captions, 576 distinct for the 78 YCB
        # meshes): each distinct text is encoded once
        texts = [t or "" for t in captions.column("caption").to_pylist()]
        distinct = list(dict.fromkeys(texts))
        at = {t: i for i, t in enumerate(distinct)}
        return np.asarray(self.model.encode_text(distinct))[[at[t] for t in texts]]


class ImageEmbedStage(EmbedStage):
    """Embeds every view with one of the profile's image encoders (``view_encoder`` or ``clip_image_encoder``)."""

    def _encode(self, views: pa.Table):
        from pipeline.onboard.stages import decoded
        from pipeline.onboard.stages.patches import memo_kind

        pngs = views.column("image").to_pylist()
        images = [decoded.decoded_view(b) for b in pngs]
        both = getattr(self.model, "encode_image_patches", None)
        if self.role != "learned_encoder" or both is None or not decoded.sharing():
            return self.model.encode_image(images)
        # the learned encoder's object patch tokens come from the same forward pass: kept for the
        # batch's ``patches`` stage (pipeline/onboard/stages/patches.py), which then runs no encoder
        vecs, kept = both(images)
        kind = memo_kind(self.spec)
        for png, tokens in zip(pngs, kept, strict=True):
            decoded.remember(kind, png, tokens)
        return vecs

"""Embedding stages: captions -> text embeddings, views -> image embeddings (L2-normalised, float32)."""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from pipeline import schemas
from pipeline.config import OnboardConfig
from pipeline.models.protocols import l2_normalise
from pipeline.models.registry import create_model
from pipeline.stages.base import error_row, with_errors


def _embedding_table(meta: list[dict], vectors: np.ndarray, dim: int, extra: dict) -> list[dict]:
    vecs = l2_normalise(vectors)
    if vecs.shape[1] != dim:
        raise ValueError(f"encoder returned {vecs.shape[1]}-d vectors, expected {dim}")
    return [{**m, **extra, "dim": dim, "embedding": v.tolist()} for m, v in zip(meta, vecs, strict=True)]


class TextEmbedStage:
    """Embeds every caption with the profile's text encoder."""

    role = "text_encoder"

    def __init__(self, cfg: OnboardConfig, run_id: str, model=None):
        self.cfg = cfg
        self.run_id = run_id
        self.spec = cfg.get_profile().text_encoder
        self.fingerprint = cfg.fingerprints()["embed_text"]
        self._model = model

    @property
    def model(self):
        if self._model is None:
            self._model = create_model(self.role, self.spec, **self.cfg.model_options.get(self.role, {}))
        return self._model

    @property
    def encoder_id(self) -> str:
        return self.spec.key()

    def output_schema(self) -> pa.Schema:
        return with_errors(schemas.embedding_schema(self.model.dim))

    def __call__(self, captions: pa.Table) -> pa.Table:
        out = self.output_schema()
        meta = captions.select(["mesh_id", "view_index", "fingerprint"]).to_pylist()
        texts = [t or "" for t in captions.column("caption").to_pylist()]
        extra = {"encoder_id": self.encoder_id, "fingerprint": self.fingerprint, "run_id": self.run_id}
        meta = [
            {"mesh_id": m["mesh_id"], "view_index": m["view_index"], "source_fingerprint": m["fingerprint"]}
            for m in meta
        ]
        try:
            rows = _embedding_table(meta, self.model.encode_text(texts), self.model.dim, extra)
        except Exception as exc:
            rows = [
                error_row(out, {**extra, "mesh_id": m}, exc)
                for m in dict.fromkeys(x["mesh_id"] for x in meta)
            ]
        return pa.Table.from_pylist(rows, schema=out)


class ImageEmbedStage:
    """Embeds every view with one of the profile's image encoders (``view_encoder`` or ``clip_image_encoder``)."""

    def __init__(self, cfg: OnboardConfig, run_id: str, role: str = "view_encoder", model=None):
        self.cfg = cfg
        self.run_id = run_id
        self.role = role
        self.spec = getattr(cfg.get_profile(), role)
        self.fingerprint = cfg.fingerprints()[f"embed_image:{role}"]
        self._model = model

    @property
    def model(self):
        if self._model is None:
            self._model = create_model(self.role, self.spec, **self.cfg.model_options.get(self.role, {}))
        return self._model

    @property
    def encoder_id(self) -> str:
        return self.spec.key()

    def output_schema(self) -> pa.Schema:
        return with_errors(schemas.embedding_schema(self.model.dim))

    def __call__(self, views: pa.Table) -> pa.Table:
        from pipeline.render import decode_png

        out = self.output_schema()
        meta = [
            {"mesh_id": m["mesh_id"], "view_index": m["view_index"], "source_fingerprint": m["fingerprint"]}
            for m in views.select(["mesh_id", "view_index", "fingerprint"]).to_pylist()
        ]
        extra = {"encoder_id": self.encoder_id, "fingerprint": self.fingerprint, "run_id": self.run_id}
        try:
            images = [decode_png(b) for b in views.column("image").to_pylist()]
            rows = _embedding_table(meta, self.model.encode_image(images), self.model.dim, extra)
        except Exception as exc:
            rows = [
                error_row(out, {**extra, "mesh_id": m}, exc)
                for m in dict.fromkeys(x["mesh_id"] for x in meta)
            ]
        return pa.Table.from_pylist(rows, schema=out)

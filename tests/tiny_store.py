"""Hand-made stores for the SQL tests: a few rows per table, written through ``Store.commit``.

``TinyStore`` keeps rows per run and commits each run in run-id order, so tests can state exactly which
rows exist, which are superseded and which fingerprints are current::

    t = TinyStore(tmp_path / "store")
    t.mesh("m1", "a/m1.obj")
    t.views("m1")
    t.captions("m1", ["A red box-shaped object", "A red box"])
    t.run()          # the runs row whose config makes fingerprints r1/c1/t1/i1 current
    store = t.commit()
"""

from __future__ import annotations

import json
from datetime import datetime, timedelta, timezone
from pathlib import Path

import pyarrow as pa

from pipeline import schemas
from pipeline.store import Store, slug

RUN = "20250101T000000000000Z-aaaaaa"
LIBRARY = "/library"
MODELS = {
    "captioner": "attributes:cap",
    "text_encoder": "minilm:txt",
    "view_encoder": "descriptor:desc",
    "clip_image_encoder": None,
}
FINGERPRINTS = {"render": "r1", "caption": "c1", "embed_text": "t1", "embed_image:view_encoder": "i1"}
#: 2 views per mesh keeps the tables small: 1 per ring, rings at -15 and +15 degrees
RENDER = {"cameras": "oscar", "views_per_ring": 1, "elevations_deg": [-15.0, 15.0]}


def run_time(run_id: str) -> datetime:
    """A timestamp that orders like ``run_id``: its time prefix, plus seconds for the suffix (so that
    ``...Z-aaaaaa`` < ``...Z-bbbbbb`` within one instant)."""
    stamp, _, suffix = run_id.partition("-")
    base = datetime.strptime(stamp, "%Y%m%dT%H%M%S%fZ").replace(tzinfo=timezone.utc)
    return base + timedelta(seconds=sum(ord(c) - ord("a") for c in suffix))


class TinyStore:
    """Accumulates hand-made rows per (run, dataset) and commits them through :meth:`Store.commit`."""

    def __init__(self, path: str | Path, run_id: str = RUN):
        self.path = Path(path)
        self.run_id = run_id
        self.rows: dict[str, dict[str, list[dict]]] = {}
        self.schemas: dict[str, pa.Schema] = {}

    def _add(self, dataset: str, schema: pa.Schema, row: dict, run_id: str | None) -> None:
        run = run_id or self.run_id
        self.rows.setdefault(run, {}).setdefault(dataset, []).append({**row, "run_id": run})
        self.schemas[dataset] = schema

    def mesh(
        self, mesh_id: str, source_path: str | None = None, status: str = "active", run_id: str | None = None
    ) -> None:
        row = {
            "mesh_id": mesh_id,
            "source_path": source_path or f"{mesh_id}/{mesh_id}.obj",
            "library_root": LIBRARY,
            "name": mesh_id,
            "format": "obj",
            "file_size": 100,
            "mtime_ns": 1,
            "deps": [],
            "n_vertices": 8,
            "n_faces": 12,
            "bounds_min": [0.0, 0.0, 0.0],
            "bounds_max": [1.0, 1.0, 1.0],
            "units_guess": "m",
            "scale_to_unit": 1.0,
            "status": status,
            "seen_at": run_time(run_id or self.run_id),
        }
        self._add("meshes", schemas.MESHES, row, run_id)

    def views(self, mesh_id: str, indices=(0, 1), fingerprint: str = "r1", run_id: str | None = None) -> None:
        for i in indices:
            row = {
                "mesh_id": mesh_id,
                "view_index": i,
                "azimuth_deg": 90.0 * i,
                "elevation_deg": -15.0 if i % 2 == 0 else 15.0,
                "camera_pose": [1.0 if k % 5 == 0 else 0.0 for k in range(16)],
                "yfov_deg": 40.0,
                "width": 2,
                "height": 2,
                "image": b"\x89PNG fake " + mesh_id.encode(),
                "fingerprint": fingerprint,
            }
            self._add("views", schemas.VIEWS, row, run_id)

    def captions(
        self,
        mesh_id: str,
        texts: list[str | None],
        fingerprint: str = "c1",
        captioner_id: str = "attributes:cap",
        run_id: str | None = None,
    ) -> None:
        for i, text in enumerate(texts):
            row = {
                "mesh_id": mesh_id,
                "view_index": i,
                "captioner_id": captioner_id,
                "prompt_style": "attributes",
                "prompt": "Describe the object.",
                "caption": text,
                "fingerprint": fingerprint,
                "view_fingerprint": "r1",
            }
            self._add("captions", schemas.CAPTIONS, row, run_id)

    def embeddings(
        self,
        table: str,
        mesh_id: str,
        indices=(0, 1),
        fingerprint: str | None = None,
        encoder_id: str | None = None,
        dim: int = 3,
        run_id: str | None = None,
    ) -> None:
        """Rows of ``text_embeddings`` or ``image_embeddings`` (defaults: the current encoder)."""
        text = table == "text_embeddings"
        encoder_id = encoder_id or (MODELS["text_encoder"] if text else MODELS["view_encoder"])
        fingerprint = fingerprint or ("t1" if text else "i1")
        for i in indices:
            row = {
                "mesh_id": mesh_id,
                "view_index": i,
                "encoder_id": encoder_id,
                "dim": dim,
                "embedding": [1.0] + [0.0] * (dim - 1),
                "fingerprint": fingerprint,
                "source_fingerprint": "c1" if text else "r1",
            }
            self._add(f"{table}/{slug(encoder_id)}", schemas.embedding_schema(dim), row, run_id)

    def features(
        self, mesh_id: str, indices=(0, 1), fingerprint: str = "f1", run_id: str | None = None
    ) -> None:
        """``view_features`` rows (2 keypoints per view)."""
        for i in indices:
            row = {
                "mesh_id": mesh_id,
                "view_index": i,
                "detector_id": "opencv:sift-256@384",
                "n_keypoints": 2,
                "keypoints": [0.0, 0.0, 1.0, 1.0],
                "descriptor_dim": 2,
                "descriptors": b"\x00\x01\x02\x03",
                "fingerprint": fingerprint,
                "source_fingerprint": "r1",
            }
            self._add("view_features", schemas.VIEW_FEATURES, row, run_id)

    def complete(self, mesh_id: str, caption: str = "A red box-shaped object with a matte surface") -> None:
        """An active mesh with every current output (views, captions, both embeddings)."""
        self.mesh(mesh_id)
        self.views(mesh_id)
        self.captions(mesh_id, [caption, caption])
        self.embeddings("text_embeddings", mesh_id)
        self.embeddings("image_embeddings", mesh_id)

    def error(
        self,
        stage: str,
        mesh_id: str | None,
        reason: str,
        fingerprint: str | None = None,
        source_path: str | None = None,
        error_type: str = "ValueError",
        run_id: str | None = None,
    ) -> None:
        row = {
            "stage": stage,
            "mesh_id": mesh_id,
            "source_path": source_path or (f"{mesh_id}/{mesh_id}.obj" if mesh_id else None),
            "fingerprint": fingerprint,
            "error_type": error_type,
            "reason": reason,
            "at": run_time(run_id or self.run_id),
        }
        self._add("errors", schemas.ERRORS, row, run_id)

    def run(
        self,
        run_id: str | None = None,
        fingerprints: dict[str, str] | None = None,
        models: dict | None = None,
        render: dict | None = None,
        status: str = "ok",
    ) -> None:
        """The ``runs`` row whose config (fingerprints, models, camera layout) is current if it is the
        latest with status ``ok``."""
        config = {
            "profile": "offline",
            "models": models or MODELS,
            "render": render or RENDER,
            "fingerprints": fingerprints or FINGERPRINTS,
        }
        at = run_time(run_id or self.run_id)
        row = {
            "engine": "local",
            "library_root": LIBRARY,
            "profile": "offline",
            "config_json": json.dumps(config),
            "started_at": at,
            "finished_at": at + timedelta(seconds=5),
            "n_files": 0,
            "n_added": 0,
            "n_removed": 0,
            "n_skipped": 0,
            "n_failed": 0,
            "stage_seconds_json": "{}",
            "status": status,
        }
        self._add("runs", schemas.RUNS, row, run_id)

    def commit(self) -> Store:
        """Commit every run's rows (oldest run first) and return the store, opened read-only."""
        with Store.open(self.path, create=True, writable=True) as store:
            for run in sorted(self.rows):
                tables = {
                    d: pa.Table.from_pylist(rows, schema=self.schemas[d])
                    for d, rows in self.rows[run].items()
                }
                store.commit(tables, run)
        self.rows = {}
        return Store.open(self.path)

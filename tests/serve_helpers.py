"""Helpers of the service tests: commit one more fake mesh to a store made by ``make_fake_store``."""

from __future__ import annotations

import json
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pyarrow as pa
from query_helpers import GRAY, embedding_table, fake_models


def fake_view(rgb: tuple[int, int, int], w: int, h: int, pad: int = 10):
    from PIL import Image

    arr = np.zeros((h + 2 * pad, w + 2 * pad, 3), np.uint8)
    arr[:] = GRAY
    arr[pad : pad + h, pad : pad + w] = rgb
    return Image.fromarray(arr)


def add_fake_mesh(
    store_path: str | Path,
    name: str,
    rgb: tuple[int, int, int],
    w: int,
    h: int,
    *,
    library_root: str = "/library",
    deps: list[str] = (),
    features: bool = False,
    finish: bool = True,
) -> str:
    """Commit mesh ``name`` (views of an ``rgb`` block) as a new onboarding run; returns its mesh_id.

    ``library_root``/``deps``: where ``<name>/model.obj`` and its referenced files lie (for export tests).
    ``features``: also commit (empty) ``view_features`` rows; ``finish=False``: stop before the run's
    ``runs`` commit, like a run that is still committing its tables.
    """
    from pipeline import schemas
    from pipeline.mesh.render import encode_png
    from pipeline.store import Store, new_run_id, slug

    models = fake_models()
    views = [fake_view(rgb, w, h), fake_view(rgb, int(w * 1.1), h)]
    mesh_id = f"id-{name}"
    run_id = new_run_id()
    with Store.open(store_path, writable=True) as store:
        runs = [r for r in store.read("runs").to_pylist() if r["status"] == "ok"]
        cfg = json.loads(max(runs, key=lambda r: r["run_id"])["config_json"])
        fps, keys = cfg["fingerprints"], cfg["models"]
        caps = models["text_encoder"].encode_text(models["captioner"].caption(views))
        vecs = models["view_encoder"].encode_image(views)
        mesh = {
            "mesh_id": mesh_id,
            "source_path": f"{name}/model.obj",
            "library_root": library_root,
            "name": name,
            "deps": [{"path": d, "size": 1, "mtime_ns": 0} for d in deps],
            "format": "obj",
            "status": "active",
            "seen_at": datetime.now(timezone.utc),
            "run_id": run_id,
        }
        view_rows = [
            {
                "mesh_id": mesh_id,
                "view_index": i,
                "image": encode_png(np.asarray(v)),
                "fingerprint": fps["render"],
                "run_id": run_id,
            }
            for i, v in enumerate(views)
        ]
        run = {"run_id": run_id, "profile": cfg["profile"], "config_json": json.dumps(cfg), "status": "ok"}
        feature_rows = [
            {
                "mesh_id": mesh_id,
                "view_index": i,
                "detector_id": "none",
                "n_keypoints": 0,
                "keypoints": [],
                "descriptor_dim": 128,
                "descriptors": b"",
                "fingerprint": "fp-features",
                "source_fingerprint": fps["render"],
                "run_id": run_id,
            }
            for i in range(len(views))
        ]
        store.commit(
            {
                "view_features": pa.Table.from_pylist(feature_rows, schema=schemas.VIEW_FEATURES)
                if features
                else None,
                "meshes": pa.Table.from_pylist([mesh], schema=schemas.MESHES),
                f"text_embeddings/{slug(keys['text_encoder'])}": embedding_table(
                    [mesh_id] * len(caps),
                    range(len(caps)),
                    caps,
                    keys["text_encoder"],
                    fps["embed_text"],
                    run_id,
                ),
                f"image_embeddings/{slug(keys['view_encoder'])}": embedding_table(
                    [mesh_id] * len(vecs),
                    range(len(vecs)),
                    vecs,
                    keys["view_encoder"],
                    fps["embed_image:view_encoder"],
                    run_id,
                ),
                "views": pa.Table.from_pylist(view_rows, schema=schemas.VIEWS),
                "runs": pa.Table.from_pylist([run], schema=schemas.RUNS) if finish else None,
            },
            run_id,
        )
    return mesh_id


def remove_fake_mesh(store_path: str | Path, mesh_id: str) -> None:
    """Commit a run that marks ``mesh_id`` removed (its folder left the library), like onboarding does."""
    from pipeline import schemas
    from pipeline.store import Store, latest_rows, new_run_id

    run_id = new_run_id()
    with Store.open(store_path, writable=True) as store:
        meshes = latest_rows(store.read("meshes"), list(schemas.KEYS["meshes"])).to_pylist()
        rows = [{**m, "status": "removed", "run_id": run_id} for m in meshes if m["mesh_id"] == mesh_id]
        runs = [r for r in store.read("runs").to_pylist() if r["status"] == "ok"]
        run = {**max(runs, key=lambda r: r["run_id"]), "run_id": run_id}
        store.commit(
            {
                "meshes": pa.Table.from_pylist(rows, schema=schemas.MESHES),
                "runs": pa.Table.from_pylist([run], schema=schemas.RUNS),
            },
            run_id,
        )


def enable_features(store_path: str | Path) -> None:
    """Commit a run that records local features (SIFT config) and empty ``view_features`` rows for every
    mesh: queries then verify, reading ``view_features`` lazily on their first verification."""
    from dataclasses import asdict

    from pipeline import schemas
    from pipeline.localfeat import FeatureConfig
    from pipeline.store import Store, latest_rows, new_run_id

    run_id = new_run_id()
    with Store.open(store_path, writable=True) as store:
        runs = [r for r in store.read("runs").to_pylist() if r["status"] == "ok"]
        last = max(runs, key=lambda r: r["run_id"])
        cfg = json.loads(last["config_json"])
        cfg["features"] = asdict(FeatureConfig())
        cfg["fingerprints"]["features"] = "fp-features"
        views = latest_rows(
            store.read("views", columns=["mesh_id", "view_index", "run_id"]), ["mesh_id", "view_index"]
        )
        rows = [
            {
                "mesh_id": v["mesh_id"],
                "view_index": v["view_index"],
                "detector_id": "opencv:sift-256@384",
                "n_keypoints": 0,
                "keypoints": [],
                "descriptor_dim": 128,
                "descriptors": b"",
                "fingerprint": "fp-features",
                "source_fingerprint": cfg["fingerprints"]["render"],
                "run_id": run_id,
            }
            for v in views.to_pylist()
        ]
        run = {**last, "run_id": run_id, "config_json": json.dumps(cfg)}
        store.commit(
            {
                "view_features": pa.Table.from_pylist(rows, schema=schemas.VIEW_FEATURES),
                "runs": pa.Table.from_pylist([run], schema=schemas.RUNS),
            },
            run_id,
        )

"""Helpers for onboarding tests: run a store build and compare stores by content."""

from __future__ import annotations

import pyarrow as pa

from pipeline.onboard.config import OnboardConfig
from pipeline.onboard.run import run_onboarding
from pipeline.store import Store

VOLATILE = {"run_id", "seen_at", "at"}
#: views per mesh of a default offline onboarding (4 per elevation ring: -15, +15 and +45 deg)
_RENDER = OnboardConfig().render
V = _RENDER.views_per_ring * len(_RENDER.elevations_deg)
#: the tables two stores are compared by (:func:`content`, :func:`assert_same_tables`)
COMPARED = (
    "meshes",
    "views",
    "captions",
    "view_features",
    "view_patches",
    "errors",
    "text_embeddings",
    "image_embeddings",
)


def onboard(library, store, models=None, **cfg):
    cfg.setdefault("workers", 0)
    return run_onboarding(str(library), str(store), OnboardConfig(**cfg), progress=False, models=models)


def content(store_path, table_filter=lambda d: d.split("/")[0] != "runs") -> dict[str, list]:
    """Every dataset's rows without run-dependent columns, sorted: equal stores compare equal."""
    s = Store.open(store_path)
    out = {}
    for table in COMPARED:
        for d in s.datasets(table):
            if not table_filter(d):
                continue
            t = s.read_latest(d) if table != "errors" else s.read(d)
            # patch tokens depend (in the last float16 bit) on how the encoder batched the views:
            # assert_same_tables compares them within a tolerance
            t = t.drop_columns([c for c in t.column_names if c in VOLATILE or c == "tokens"])
            out[d] = sorted(map(repr, t.to_pylist()))
    return out


def count(store_path, dataset: str) -> int:
    return Store.open(store_path).read(dataset).num_rows


def table(store_path, dataset: str) -> pa.Table:
    return Store.open(store_path).read(dataset)


def assert_same_tables(store_a, store_b, atol: float = 1e-5) -> None:
    """The two stores hold the same rows (run-dependent columns aside); embedding vectors may differ by
    ``atol``: a text encoder's float results depend slightly on how captions were batched."""
    import numpy as np

    a, b = Store.open(store_a), Store.open(store_b)
    for table in COMPARED:
        assert a.datasets(table) == b.datasets(table), table
        for d in a.datasets(table):
            ta, tb = (s.read_latest(d) if table != "errors" else s.read(d) for s in (a, b))
            drop = [c for c in ta.column_names if c in VOLATILE]
            ta, tb = ta.drop_columns(drop), tb.drop_columns(drop)
            key = [c for c in ta.column_names if c in ("mesh_id", "view_index", "fingerprint", "source_path")]
            ta, tb = ta.sort_by([(k, "ascending") for k in key]), tb.sort_by([(k, "ascending") for k in key])
            if "embedding" in ta.column_names:
                va, vb = (np.array(t.column("embedding").to_pylist(), dtype=np.float64) for t in (ta, tb))
                assert va.shape == vb.shape and np.allclose(va, vb, atol=atol), d
                ta, tb = ta.drop_columns(["embedding"]), tb.drop_columns(["embedding"])
            if "tokens" in ta.column_names:  # patch tokens, float16: the same up to the encoder's batching
                for ra, rb in zip(ta.to_pylist(), tb.to_pylist(), strict=True):
                    xa, xb = (np.frombuffer(r["tokens"] or b"", "<f2").astype(np.float64) for r in (ra, rb))
                    assert xa.shape == xb.shape and np.allclose(xa, xb, atol=1e-2), d
                ta, tb = ta.drop_columns(["tokens"]), tb.drop_columns(["tokens"])
            assert ta.to_pylist() == tb.to_pylist(), d

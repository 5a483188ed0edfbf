"""Helpers for the Ray engine tests: compare stores built by different engines, check for duplicates."""

from __future__ import annotations

import numpy as np

from pipeline import schemas
from pipeline.store import Store, table_of

VOLATILE = {"run_id", "seen_at", "at"}
TABLES = ("meshes", "views", "captions", "errors", "text_embeddings", "image_embeddings", "view_features")


def store_rows(path) -> dict[str, list[dict]]:
    """Latest rows of every dataset (all errors rows), run-dependent columns dropped, in a stable order."""
    s = Store.open(path)
    out = {}
    for table in TABLES:
        for d in s.datasets(table):
            t = s.read_latest(d) if table != "errors" else s.read(d)
            t = t.drop_columns([c for c in t.column_names if c in VOLATILE])
            rows = t.to_pylist()
            out[d] = sorted(rows, key=lambda r: repr({k: v for k, v in r.items() if k != "embedding"}))
    return out


def assert_same_store(a, b) -> None:
    """Equal tables; embedding vectors equal up to float32 rounding (the text encoder pads per batch)."""
    ra, rb = store_rows(a), store_rows(b)
    assert sorted(ra) == sorted(rb)
    for dataset, rows in ra.items():
        assert len(rows) == len(rb[dataset]), dataset
        for x, y in zip(rows, rb[dataset], strict=True):
            ex, ey = x.pop("embedding", None), y.pop("embedding", None)
            assert x == y, dataset
            if ex is not None:
                assert np.allclose(ex, ey, atol=1e-6), dataset


def assert_no_duplicates(path) -> None:
    """No row key was committed twice (a batch committed and then redone would repeat its keys)."""
    s = Store.open(path)
    for table in TABLES:
        key = schemas.KEYS.get(table)
        for d in s.datasets(table):
            if not key or table_of(d) == "meshes":  # meshes rows are re-stated by design (seen_at)
                continue
            t = s.read(d, columns=list(key))
            keys = list(zip(*(t.column(c).to_pylist() for c in key), strict=True))
            assert len(keys) == len(set(keys)), f"{d}: {len(keys) - len(set(keys))} duplicate rows"
        if table == "errors":
            t = s.read("errors", columns=["mesh_id", "stage", "fingerprint"])
            rows = [r for r in zip(*(c.to_pylist() for c in t.columns), strict=True) if r[0]]
            assert len(rows) == len(set(rows)), "errors: duplicate rows"

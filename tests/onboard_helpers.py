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


def onboard(library, store, models=None, **cfg):
    cfg.setdefault("workers", 0)
    return run_onboarding(str(library), str(store), OnboardConfig(**cfg), progress=False, models=models)


def content(store_path, table_filter=lambda d: d.split("/")[0] != "runs") -> dict[str, list]:
    """Every dataset's rows without run-dependent columns, sorted: equal stores compare equal."""
    s = Store.open(store_path)
    out = {}
    tables = ("meshes", "views", "captions", "view_features", "errors", "text_embeddings", "image_embeddings")
    for table in tables:
        for d in s.datasets(table):
            if not table_filter(d):
                continue
            t = s.read_latest(d) if table != "errors" else s.read(d)
            t = t.drop_columns([c for c in t.column_names if c in VOLATILE])
            out[d] = sorted(map(repr, t.to_pylist()))
    return out


def count(store_path, dataset: str) -> int:
    return Store.open(store_path).read(dataset).num_rows


def table(store_path, dataset: str) -> pa.Table:
    return Store.open(store_path).read(dataset)

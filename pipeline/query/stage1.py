"""Stage 1, the text filter: DuckDB runs ``sql/stage1_text_filter.sql`` over the caption table.

The caption table (``mesh_idx``, ``embedding FLOAT[dim]``) is registered once on a long-lived connection;
each query binds its vector, tau and k as parameters, so no user text or path ever reaches SQL text.
See docs/query.md for what this layout buys over scanning the store's Parquet parts.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import pyarrow as pa

from pipeline.db import load_sql


@dataclass
class Stage1Result:
    mesh_idx: np.ndarray  # int32, best first
    scores: np.ndarray  # float32, same order
    used_fallback: bool
    seconds: float


class TextFilter:
    """Warm DuckDB connection over one caption table."""

    def __init__(self, captions: pa.Table, threads: int | None = None) -> None:
        import duckdb

        self.con = duckdb.connect(":memory:")
        if threads:
            self.con.execute("SET threads = ?", [int(threads)])
        self.n_rows = captions.num_rows
        emb_type = captions.schema.field("embedding").type
        self.dim = getattr(emb_type, "list_size", None) or 0
        self._captions = captions.select(["mesh_idx", "embedding"])
        self.con.register("stage1_captions", self._captions)
        self.sql = load_sql("stage1_text_filter")

    def run(self, query: np.ndarray, threshold: float | None, fallback_k: int) -> Stage1Result:
        """Models scoring >= ``threshold`` (best first), else the ``fallback_k`` best; ``None`` = top-k only."""
        q = np.asarray(query, dtype=np.float32).reshape(-1)
        if self.dim and q.shape[0] != self.dim:
            raise ValueError(f"query vector has {q.shape[0]} dims, captions have {self.dim}")
        t0 = time.perf_counter()
        params = {
            "query": q.tolist(),
            "threshold": None if threshold is None else float(threshold),
            "fallback_k": int(fallback_k),
        }
        out = self.con.execute(self.sql, params).fetchnumpy()
        seconds = time.perf_counter() - t0
        idx = np.asarray(out["mesh_idx"], dtype=np.int32)
        scores = np.asarray(out["score"], dtype=np.float32)
        used = bool(len(out["used_fallback"]) and out["used_fallback"][0])
        return Stage1Result(idx, scores, used, seconds)

    def close(self) -> None:
        self.con.close()

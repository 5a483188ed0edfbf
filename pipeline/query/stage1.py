"""Stage 1, the text filter: DuckDB runs ``sql/stage1_text_filter.sql`` over the caption table.

The table is registered on warm connections; each query binds its vector, tau and k as parameters, so no
user text or path ever reaches SQL text. A DuckDB connection runs one statement at a time (and a cursor
does not see the Arrow tables registered on its parent), so concurrent callers each borrow their own
connection from a small pool: the Python API and the HTTP service are thread-safe.

Layout: every caption vector is cut into ``SLICES`` equal slices, stored as columns ``e0..e7``
(``FLOAT[dim/8]``, zero-padded when dim is not a multiple of 8), and the SQL sums eight
``list_dot_product`` calls. DuckDB's dot product is one dependent chain of float additions per row; eight
short chains instead of one long one let the CPU overlap them, which cuts stage 1's CPU time by about a
third at 1M rows (docs/performance.md (Query)). The sum is the same inner product up to float rounding (~1e-7).

:meth:`TextFilter.run_blas` computes the inner products with NumPy (BLAS, one matrix-vector product over a
contiguous copy of the vectors made on first use), takes the max per model (one ``reduceat`` over rows grouped by model once), and lets
``sql/stage1_select.sql`` apply tau and the fallback: DuckDB's ``list_dot_product`` made the all-SQL
version 3.1x the NumPy floor at 1M rows, this one is within 2x (docs/performance.md, "Stage-1 index").
:meth:`TextFilter.run` (what queries use) picks by size: the all-SQL statement (:meth:`TextFilter.run_sql`,
the reference) below :data:`BLAS_MIN_ROWS` caption rows, where it costs well under a millisecond and its
float rounding is what the golden rankings (tests/golden) pin; ``run_blas`` from there on, where the SQL's
dot products are the cost. Both give the same models in the same order; scores agree to ~1e-7.
"""

from __future__ import annotations

import queue
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import pyarrow as pa

from pipeline.db import load_sql

SLICES = 8
#: What the fallback top-k counts: caption rows (paper, reference scripts) or models.
FALLBACK_UNITS = ("captions", "meshes")
#: rows per Arrow record batch: DuckDB scans batches in parallel
BATCH_ROWS = 65536
#: from this many caption rows on, :meth:`TextFilter.run` computes the inner products with BLAS ...
BLAS_MIN_ROWS = 100_000
#: ... while its contiguous copy of the vectors stays this small (past it, the memory-mapped SQL scan;
#: stores that large use the index by default, ``--stage1 auto``)
BLAS_MAX_BYTES = 4 << 30


@dataclass
class Stage1Result:
    mesh_idx: np.ndarray  # int32, best first
    scores: np.ndarray  # float32, same order
    used_fallback: bool
    seconds: float


def checked_query(query, dim: int, fallback_unit: str) -> np.ndarray:
    """``query`` as a flat float32 vector of width ``dim``; ValueError for another width or an unknown
    fallback unit (the one check of every stage-1 engine: exact scan and vector index)."""
    if fallback_unit not in FALLBACK_UNITS:
        raise ValueError(f"unknown fallback unit {fallback_unit!r}; choose from {', '.join(FALLBACK_UNITS)}")
    q = np.asarray(query, dtype=np.float32).reshape(-1)
    if q.shape[0] != dim:
        raise ValueError(f"query vector has {q.shape[0]} dims, captions have {dim}")
    return q


def vectors(table: pa.Table, column: str = "embedding") -> np.ndarray:
    """(n, dim) float32 view of a ``fixed_size_list<float32>`` column."""
    col = table.column(column).combine_chunks()
    dim = col.type.list_size
    flat = col.flatten().to_numpy(zero_copy_only=False)
    return np.asarray(flat, dtype=np.float32).reshape(len(col), dim)


def slice_layout(captions: pa.Table) -> pa.Table:
    """``(mesh_idx, embedding FLOAT[dim])`` -> ``(mesh_idx, e0..e7 FLOAT[ceil(dim/8)])`` in batches."""
    x = vectors(captions)
    n, dim = x.shape
    width = -(-dim // SLICES)
    if width * SLICES != dim:
        x = np.pad(x, ((0, 0), (0, width * SLICES - dim)))  # zeros add nothing to a dot product
    cols = {"mesh_idx": captions.column("mesh_idx").combine_chunks().cast(pa.int32())}
    for i in range(SLICES):
        part = np.ascontiguousarray(x[:, i * width : (i + 1) * width]).reshape(-1)
        cols[f"e{i}"] = pa.FixedSizeListArray.from_arrays(pa.array(part), width)
    table = pa.table(cols).replace_schema_metadata({"dim": str(dim)})
    return pa.Table.from_batches(table.to_batches(max_chunksize=BATCH_ROWS), schema=table.schema)


def query_params(query: np.ndarray, width: int) -> dict[str, list[float]]:
    """The query vector cut like the table: ``{"q0": [...], ..., "q7": [...]}``."""
    q = np.zeros(width * SLICES, np.float32)
    q[: len(query)] = query
    return {f"q{i}": q[i * width : (i + 1) * width].tolist() for i in range(SLICES)}


class TextFilter:
    """Warm DuckDB connection over one caption table (plain or already sliced, see :func:`slice_layout`)."""

    def __init__(self, captions: pa.Table, threads: int | None = None, dim: int | None = None) -> None:
        import duckdb

        if "embedding" in captions.column_names:
            dim = captions.schema.field("embedding").type.list_size
            captions = slice_layout(captions)
        self.table = captions
        self.width = captions.schema.field("e0").type.list_size
        meta = captions.schema.metadata or {}
        self.dim = int(meta.get(b"dim", dim or self.width * SLICES))
        self.n_rows = captions.num_rows
        self.threads = threads
        self.sql = load_sql("stage1_text_filter")
        self.select_sql = load_sql("stage1_select")
        self._kernel: tuple | None = None
        self._idle: queue.SimpleQueue = queue.SimpleQueue()  # warm connections not in use
        self._all: list = []
        self._lock = threading.Lock()
        self._kernel_lock = threading.Lock()
        self._duckdb = duckdb
        self._idle.put(self._connect())  # one warm connection up front (and early errors)

    def _connect(self):
        con = self._duckdb.connect(":memory:")
        if self.threads:
            con.execute("SET threads = ?", [int(self.threads)])
        con.register("stage1_captions", self.table)  # zero-copy: every connection scans the same Arrow data
        with self._lock:
            self._all.append(con)
        return con

    @contextmanager
    def connection(self):
        """Borrow a warm connection (a new one when all are busy; it joins the pool afterwards)."""
        try:
            con = self._idle.get_nowait()
        except queue.Empty:
            con = self._connect()
        try:
            yield con
        finally:
            self._idle.put(con)

    @property
    def con(self):
        """The first connection (single-threaded callers and tests)."""
        return self._all[0]

    def _vector(self, query: np.ndarray) -> np.ndarray:
        v = np.asarray(query, dtype=np.float32).reshape(-1)
        if v.shape[0] != self.dim:
            raise ValueError(f"query vector has {v.shape[0]} dims, captions have {self.dim}")
        return v

    def caption_scores(self, query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(mesh_idx, cosine) of every caption row, in table order (evaluation's view-level text ranking)."""
        v = self._vector(query)
        if not self.n_rows:
            return np.zeros(0, np.int32), np.zeros(0, np.float32)
        rows, _ = self.scores(v)
        return self._kernel_parts()[4], rows

    def model_scores(self, query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(mesh_idx, max cosine over its captions) of every model with captions (the fusion's text terms)."""
        v = self._vector(query)
        if not self.n_rows:
            return np.zeros(0, np.int32), np.zeros(0, np.float32)
        return self.scores(v)[1]

    def _kernel_parts(self) -> tuple:
        """(the caption matrix (rows, width x 8) float32, row order by model, group starts, model per group,
        model per row), built once.

        One contiguous matrix, so a query is one BLAS matrix-vector product: a product per record batch
        and slice (128 calls at 1M rows) cost 6x more under load, in thread start-up, than the one call.
        The copy replaces the memory-mapped slices in the hot path (their pages are no longer touched)."""
        with self._kernel_lock:  # built once, also when concurrent queries arrive first together
            if self._kernel is None:
                self._kernel = self._build_kernel()
        return self._kernel

    def _build_kernel(self) -> tuple:
        x = np.empty((self.n_rows, self.width * SLICES), np.float32)
        offset = 0
        for batch in self.table.to_batches():
            for i in range(SLICES):
                col = batch.column(f"e{i}")
                flat = np.asarray(col.flatten().to_numpy(zero_copy_only=False), np.float32)
                x[offset : offset + len(col), i * self.width : (i + 1) * self.width] = flat.reshape(
                    len(col), self.width
                )
            offset += batch.num_rows
        mesh = self.table.column("mesh_idx").to_numpy().astype(np.int32)
        order = np.argsort(mesh, kind="stable")
        sm = mesh[order]
        starts = np.flatnonzero(np.concatenate(([True], sm[1:] != sm[:-1]))) if len(sm) else sm
        return x, order, starts, sm[starts].astype(np.int32), mesh

    def scores(self, query: np.ndarray) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
        """(per caption row: inner product, per model: (mesh_idx, max over its captions)) for ``query``."""
        x, order, starts, models, _ = self._kernel_parts()
        q = np.zeros(self.width * SLICES, np.float32)
        q[: self.dim] = query
        out = x @ q
        best = np.maximum.reduceat(out[order], starts) if len(out) else out
        return out, (models, best)

    def run(
        self, query: np.ndarray, threshold: float | None, fallback_k: int, fallback_unit: str = "captions"
    ) -> Stage1Result:
        """Models scoring >= ``threshold`` (best first); when none does (or ``threshold`` is ``None``) the
        fallback: the distinct models of the ``fallback_k`` best captions (``fallback_unit="captions"``, the
        paper's) or the ``fallback_k`` best models (``"meshes"``). :meth:`run_sql` below
        :data:`BLAS_MIN_ROWS` caption rows and past :data:`BLAS_MAX_BYTES` of vectors, :meth:`run_blas`
        between (the same answer)."""
        copy_bytes = self.n_rows * self.width * SLICES * 4
        blas = BLAS_MIN_ROWS <= self.n_rows and (copy_bytes <= BLAS_MAX_BYTES or self._kernel is not None)
        kernel = self.run_blas if blas else self.run_sql
        return kernel(query, threshold, fallback_k, fallback_unit)

    def run_sql(
        self, query: np.ndarray, threshold: float | None, fallback_k: int, fallback_unit: str = "captions"
    ) -> Stage1Result:
        """:meth:`run` all in SQL (``sql/stage1_text_filter.sql``): the reference."""
        q, params = self._check(query, threshold, fallback_k, fallback_unit)
        t0 = time.perf_counter()
        with self.connection() as con:
            out = con.execute(self.sql, {**query_params(q, self.width), **params}).fetchnumpy()
        return self._result(out, time.perf_counter() - t0)

    def run_blas(
        self, query: np.ndarray, threshold: float | None, fallback_k: int, fallback_unit: str = "captions"
    ) -> Stage1Result:
        """:meth:`run` with the inner products computed by BLAS and only the selection in SQL
        (``sql/stage1_select.sql``): the same answer, scores equal up to float rounding (~1e-7)."""
        q, params = self._check(query, threshold, fallback_k, fallback_unit)
        t0 = time.perf_counter()
        rows, (models, best) = self.scores(q)
        _, order, starts, _, mesh = self._kernel_parts()
        # the SQL reads only the captions of the fallback_k best models: hand it those of every model
        # scoring at least the k-th best (ties included), a superset, so the answer is the same
        k = int(fallback_k)
        if len(best) > k:
            kth = np.partition(best, len(best) - k)[len(best) - k]
            groups = np.flatnonzero(best >= kth)
            ends = np.append(starts[1:], len(order))
            sel = order[np.concatenate([np.arange(starts[g], ends[g]) for g in groups])]
            caption_scores = pa.table({"mesh_idx": mesh[sel], "score": rows[sel]})
        else:
            caption_scores = pa.table({"mesh_idx": mesh, "score": rows})
        model_scores = pa.table({"mesh_idx": models, "score": best})
        with self.connection() as con:
            con.register("stage1_mesh_scores", model_scores)
            con.register("stage1_caption_scores", caption_scores)
            try:
                out = con.execute(self.select_sql, params).fetchnumpy()
            finally:
                con.unregister("stage1_mesh_scores")
                con.unregister("stage1_caption_scores")
        return self._result(out, time.perf_counter() - t0)

    def _check(self, query, threshold, fallback_k, fallback_unit) -> tuple[np.ndarray, dict]:
        q = checked_query(query, self.dim, fallback_unit)
        params = {
            "threshold": None if threshold is None else float(threshold),
            "fallback_k": int(fallback_k),
            "fallback_unit": fallback_unit,
        }
        return q, params

    @staticmethod
    def _result(out: dict, seconds: float) -> Stage1Result:
        idx = np.asarray(out["mesh_idx"], dtype=np.int32)
        scores = np.asarray(out["score"], dtype=np.float32)
        used = bool(len(out["used_fallback"]) and out["used_fallback"][0])
        return Stage1Result(idx, scores, used, seconds)

    def close(self) -> None:
        with self._lock:
            cons, self._all = self._all, []
        for con in cons:
            con.close()

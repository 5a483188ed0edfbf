"""Stage 1 answered from the index: one consistent, read-only snapshot of an index directory.

The search keeps the exact path's semantics (``sql/stage1_text_filter.sql``):

* tau: an IVF range search at ``tau - eps`` (``eps``: the codec's error bound on an inner product,
  measured at build, see :mod:`pipeline.index.build`) over the base, an exact scan of the small delta.
  The lists searched follow tau when the build calibrated a probe depth ``delta`` (manifest ``probe``):
  every list whose centroid scores >= ``tau - delta`` against the query, at least ``min_lists`` of
  them (:func:`probe_lists`); otherwise the manifest's fixed ``nprobe`` best lists;
  every model with a surviving caption is rescored exactly (all its captions, float32, from the
  vector file, read by row), score = max over its captions, kept when >= tau;
* nothing passes (or no tau): a k-NN search of the caption rows finds the candidate models, rescored the
  same way (with a calibrated depth: the k-th best coded score in the query's best lists, minus eps,
  bounds the k-th best exact score from below, and a tau search there finds the true top k); then the
  fallback counts ``fallback_k`` caption rows (the paper's) or models, like the SQL.

Returned scores are therefore exact inner products; what the index can lose is a model none of whose
captions lies in the probed lists (measured as tau-set recall by ``bench/bench_stage1_index.py``).
"""

from __future__ import annotations

import os
import time
from functools import cached_property
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from pipeline.index.layout import base_array, check_files
from pipeline.index.lookup import read_ids
from pipeline.query.stage1 import Stage1Result, checked_query


class IndexDamaged(RuntimeError):
    """The index directory cannot be read as its manifest describes."""


def _ranges(starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """Concatenation of ``arange(s, e)`` for each pair (vectorised)."""
    lens = ends - starts
    total = int(lens.sum())
    if total == 0:
        return np.zeros(0, np.int64)
    offs = np.repeat(starts - np.concatenate(([0], np.cumsum(lens)[:-1])), lens)
    return np.arange(total, dtype=np.int64) + offs


def per_mesh_max(mesh_idx: np.ndarray, scores: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(distinct mesh_idx, max score), any order."""
    if not len(mesh_idx):
        return np.zeros(0, np.int32), np.zeros(0, np.float32)
    order = np.lexsort((-scores, mesh_idx))
    m, s = mesh_idx[order], scores[order]
    first = np.concatenate(([True], m[1:] != m[:-1]))
    return m[first].astype(np.int32), s[first]


def row_scores(rows: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``rows @ q`` without BLAS: right after a faiss search its OpenMP threads still spin, and a BLAS
    product waits on them (8,008 x 384: 4.05 ms instead of 0.27 ms idle; this loop takes 0.64 ms;
    `bench/bench_blas_after_faiss.py`)."""
    return np.einsum("ij,j->i", rows, q)


def probe_count(sorted_cs: np.ndarray, tau: float, delta: float, min_lists: int) -> int:
    """How many lists a tau search probes, given every centroid's score against the query best first:
    those scoring >= ``tau - delta``, and at least the ``min_lists`` best."""
    n = int(np.searchsorted(-sorted_cs, -np.float32(tau - delta), side="right"))
    return min(len(sorted_cs), max(min_lists, n))


def probe_lists(cs: np.ndarray, tau: float, delta: float, min_lists: int) -> np.ndarray:
    """The lists (best first) a tau search probes, from the centroid scores ``cs`` in list order."""
    order = np.argsort(-cs, kind="stable")
    return order[: probe_count(cs[order], tau, delta, min_lists)].astype(np.int64)


def _ivf_params(nprobe: int):
    """faiss IVF search parameters probing ``nprobe`` lists (per call: concurrent queries share the index)."""
    import faiss

    params = faiss.SearchParametersIVF()
    params.nprobe = int(nprobe)
    return params


class QueryScores:
    """One query against one snapshot; what the tau search and the fallback both need is computed once:
    every centroid's score, best first, and the delta rows' exact scores (dead rows -inf)."""

    def __init__(self, snap: IndexSnapshot, q: np.ndarray) -> None:
        self.snap, self.q = snap, q
        self.x = np.ascontiguousarray(q[None, :], np.float32)

    @cached_property
    def ranked(self) -> tuple[np.ndarray, np.ndarray]:
        """(centroid scores, lists), best first, from faiss (a NumPy product here would wait on BLAS
        threads while faiss's OpenMP threads spin after the previous search; bench/bench_blas_after_faiss.py)."""
        import faiss

        ivf = faiss.extract_index_ivf(self.snap.index)
        cs, order = ivf.quantizer.search(self.x, ivf.nlist)
        return cs[0], order[0]

    @cached_property
    def delta(self) -> np.ndarray:
        return self.snap._delta_scores(self.q)


class IndexSnapshot:
    """The index as its manifest described it when opened, numbered against ``active_ids`` (sorted mesh
    ids of the active meshes: ``mesh_idx`` is the position in it, as on the exact path)."""

    def __init__(self, directory: Path, man: dict, active_ids: pa.Array) -> None:
        import faiss

        problem = check_files(directory, man)
        if problem:
            raise IndexDamaged(problem)
        self.directory, self.manifest = directory, man
        self.dim = int(man["dim"])
        self.eps = float(man["eps"])
        self.nprobe = int(man["nprobe"])
        probe = man.get("probe") or {}
        self.probe_delta = probe.get("delta")  # None: the fixed nprobe (an index built before it existed)
        self.min_lists = int(probe.get("min_lists", 1))
        try:
            self.index = faiss.read_index(str(directory / man["base"]["faiss"]))
            base_mesh = base_array(directory, man, "mesh_code", mmap=False).astype(np.int32, copy=False)
            self.by_mesh = base_array(directory, man, "by_mesh", mmap=False).astype(np.int64, copy=False)
            self.mesh_start = base_array(directory, man, "mesh_start", mmap=False).astype(np.int64, copy=False)
            with np.load(directory / man["delta"]["file"], allow_pickle=False) as d:
                d_mesh = d["mesh_code"].astype(np.int32)
                dead = d["dead"].astype(np.int64)
            base_ids = read_ids(directory / man["base"]["meshes"])
        except (OSError, RuntimeError, ValueError, KeyError, pa.ArrowException) as exc:
            raise IndexDamaged(f"{directory}: {str(exc).splitlines()[0][:120]}") from None
        n_base, n_slots = int(man["base"]["n_slots"]), int(man["n_slots"])
        if len(base_mesh) != n_base or n_base + len(d_mesh) != n_slots or self.index.d != self.dim:
            raise IndexDamaged(f"{directory}: slot counts do not match the manifest")
        if self.index.ntotal != man["base"]["ntotal"]:
            raise IndexDamaged(f"{directory}: the IVF file holds {self.index.ntotal} rows, not as recorded")
        self.index.nprobe = self.nprobe
        # one query at a time: faiss's default splits the work by query, so a single query scanned its
        # lists on one thread; mode 1 splits the probed lists between the threads (same results)
        faiss.extract_index_ivf(self.index).parallel_mode = 1
        q = getattr(self.index, "quantizer", None)
        if q is not None and hasattr(faiss.downcast_index(q), "hnsw"):
            faiss.downcast_index(q).hnsw.efSearch = max(64, 2 * self.nprobe)
        self.n_base, self.n_slots = n_base, n_slots
        all_ids = pa.concat_arrays([base_ids, pa.array(man["delta"]["meshes"], pa.string())])
        self.code_to_idx = (
            pc.index_in(all_ids, value_set=active_ids).fill_null(-1).to_numpy().astype(np.int32)
        )
        self.slot_mesh = np.concatenate([base_mesh, d_mesh])
        self.alive = np.ones(n_slots, bool)
        self.alive[dead] = False
        # survivors' rows are read with pread, not through a memory map: pages a map touched would count
        # in this process's resident memory (the file is 1.5 KB x rows: 15 GB at 10M rows of 384-d)
        self._fd = os.open(directory / man["vectors"], os.O_RDONLY)
        self.delta_vecs = self.read_rows(np.arange(n_base, n_slots))  # small: kept resident
        self.delta_alive = self.alive[n_base:]
        self.n_base_meshes = len(self.mesh_start) - 1
        order = np.argsort(d_mesh, kind="stable")
        self.delta_by_mesh = order + n_base
        self.delta_codes = d_mesh[order]
        live = self.alive & (self.code_to_idx[self.slot_mesh] >= 0)
        self.n_rows = int(live.sum())  # caption rows a query can see

    # ------------------------------------------------------------------ helpers
    def read_rows(self, slots: np.ndarray) -> np.ndarray:
        """Float32 rows of sorted ``slots`` from the vector file (one read per run of consecutive slots)."""
        out = np.empty((len(slots), self.dim), np.float32)
        if not len(slots):
            return out
        row = self.dim * 4
        breaks = np.flatnonzero(np.diff(slots) != 1) + 1
        starts = np.concatenate(([0], breaks))
        ends = np.concatenate((breaks, [len(slots)]))
        for a, b in zip(starts.tolist(), ends.tolist(), strict=True):
            buf = os.pread(self._fd, (b - a) * row, int(slots[a]) * row)
            if len(buf) != (b - a) * row:
                raise IndexDamaged(f"{self.directory / self.manifest['vectors']} is shorter than its rows")
            out[a:b] = np.frombuffer(buf, np.float32).reshape(b - a, self.dim)
        return out

    def _slots_of(self, codes: np.ndarray) -> np.ndarray:
        """Live slots of the mesh ``codes`` (base via the by-mesh order, delta by search)."""
        b = codes[codes < self.n_base_meshes]
        base = self.by_mesh[_ranges(self.mesh_start[b], self.mesh_start[b + 1])] if len(b) else []
        lo = np.searchsorted(self.delta_codes, codes, "left")
        hi = np.searchsorted(self.delta_codes, codes, "right")
        delta = self.delta_by_mesh[_ranges(lo, hi)]
        slots = np.concatenate([np.asarray(base, np.int64), delta])
        return slots[self.alive[slots]]

    def _rescore(self, q: np.ndarray, codes: np.ndarray):
        """(slots, their mesh_idx, exact scores) of every live caption of the active ``codes``."""
        codes = np.unique(codes)
        codes = codes[self.code_to_idx[codes] >= 0]
        slots = np.sort(self._slots_of(codes))  # sorted: the file is read front to back
        scores = row_scores(self.read_rows(slots), q) if len(slots) else np.zeros(0, np.float32)
        return slots, self.code_to_idx[self.slot_mesh[slots]], scores.astype(np.float32)

    def _delta_scores(self, q: np.ndarray) -> np.ndarray:
        s = row_scores(self.delta_vecs, q) if len(self.delta_vecs) else np.zeros(0, np.float32)
        return np.where(self.delta_alive, s, -np.inf)

    # ------------------------------------------------------------------ search
    def query_scores(self, q: np.ndarray) -> QueryScores:
        """What one query scores against this snapshot, each part computed once (:class:`QueryScores`)."""
        return QueryScores(self, q)

    def _tau_candidates(self, qs: QueryScores, tau: float) -> np.ndarray:
        radius = float(tau) - self.eps
        if self.index.ntotal:
            labels = self._range_search(qs, float(tau), radius)
            labels = labels[self.alive[labels]]
        else:
            labels = np.zeros(0, np.int64)
        d = np.flatnonzero(qs.delta >= radius) + self.n_base
        return self.slot_mesh[np.concatenate([labels, d])]

    def probed_lists(self, q: np.ndarray | QueryScores, tau: float) -> tuple[np.ndarray, np.ndarray]:
        """(lists, their centroid scores), best first, that a tau search probes with the calibrated depth."""
        cs, order = (q if isinstance(q, QueryScores) else self.query_scores(q)).ranked
        n = probe_count(cs, tau, float(self.probe_delta), self.min_lists)
        return np.ascontiguousarray(order[:n], np.int64), np.ascontiguousarray(cs[:n], np.float32)

    def _range_search(self, qs: QueryScores, tau: float, radius: float) -> np.ndarray:
        """Base slots whose coded score is >= ``radius`` in the lists the query probes."""
        import faiss

        if self.probe_delta is None:
            return self.index.range_search(qs.x, radius)[2]
        keys, dis = self.probed_lists(qs, tau)
        res = faiss.RangeSearchResult(1)
        faiss.extract_index_ivf(self.index).range_search_preassigned_c(
            1, faiss.swig_ptr(qs.x), radius, faiss.swig_ptr(keys), faiss.swig_ptr(dis), res, False,
            _ivf_params(len(keys)), None,
        )  # fmt: skip
        n = int(faiss.rev_swig_ptr(res.lims, 2)[1])
        return faiss.rev_swig_ptr(res.labels, n).copy() if n else np.zeros(0, np.int64)

    def _knn_candidates(self, qs: QueryScores, k_rows: int) -> np.ndarray:
        """Mesh codes of (about) the ``k_rows`` best live caption rows of active meshes."""
        if self.probe_delta is not None and self.index.ntotal:
            codes = self._knn_by_probe(qs, k_rows)
            if codes is not None:
                return codes
        want = k_rows
        while True:
            k = min(want, max(self.index.ntotal, 1))
            if self.index.ntotal:
                dist, labels = self.index.search(qs.x, k)
                ok = labels[0] >= 0
                dist, labels = dist[0][ok], labels[0][ok]
                keep = self.alive[labels] & (self.code_to_idx[self.slot_mesh[labels]] >= 0)
                dist, labels = dist[keep], labels[keep]
            else:
                dist, labels = np.zeros(0, np.float32), np.zeros(0, np.int64)
            ds = qs.delta
            dl = np.flatnonzero(np.isfinite(ds) & (self.code_to_idx[self.slot_mesh[self.n_base :]] >= 0))
            codes = self.slot_mesh[np.concatenate([labels, dl + self.n_base])]
            if len(labels) + len(dl) >= k_rows or k >= self.index.ntotal:
                return codes
            want *= 4

    def _knn_by_probe(self, qs: QueryScores, k_rows: int) -> np.ndarray | None:
        """The k-NN candidates through the tau-following probe: the ``k_rows``-th best coded score in the
        query's best lists, minus eps, is at most the ``k_rows``-th best exact score of the whole index, so a
        tau search at that score returns every row of the true top ``k_rows`` whose list it probes. None
        when those lists hold fewer than ``k_rows`` live rows of active meshes (the fixed nprobe serves)."""
        import faiss

        keys, dis = self.probed_lists(qs, np.inf)  # the best min_lists lists
        k = int(min(self.index.ntotal, max(4 * k_rows, 256)))
        d = np.empty((1, k), np.float32)
        labels = np.empty((1, k), np.int64)
        faiss.extract_index_ivf(self.index).search_preassigned_c(
            1, faiss.swig_ptr(qs.x), k, faiss.swig_ptr(keys), faiss.swig_ptr(dis), faiss.swig_ptr(d),
            faiss.swig_ptr(labels), False, _ivf_params(len(keys)), None,
        )  # fmt: skip
        d, labels = d[0], labels[0]
        ok = labels >= 0
        d, labels = d[ok], labels[ok]
        keep = self.alive[labels] & (self.code_to_idx[self.slot_mesh[labels]] >= 0)
        if keep.sum() < k_rows:
            return None
        tau = float(np.sort(d[keep])[::-1][k_rows - 1]) - self.eps
        return self._tau_candidates(qs, tau)

    def run(
        self, query: np.ndarray, threshold: float | None, fallback_k: int, fallback_unit: str = "captions"
    ) -> Stage1Result:
        """Same contract as :meth:`pipeline.query.stage1.TextFilter.run`."""
        q = checked_query(query, self.dim, fallback_unit)
        t0 = time.perf_counter()
        k = int(fallback_k)
        qs = self.query_scores(q)
        if threshold is not None:
            _, m_idx, s = self._rescore(q, self._tau_candidates(qs, threshold))
            m, best = per_mesh_max(m_idx, s)
            keep = best >= np.float32(threshold)
            if keep.any():
                m, best = m[keep], best[keep]
                order = np.lexsort((m, -best))
                return Stage1Result(m[order], best[order], False, time.perf_counter() - t0)
        # fallback: enough caption rows that the top-k models (and their top-k captions) are among them
        _, m_idx, s = self._rescore(q, self._knn_candidates(qs, 8 * k + 64))
        m, best = per_mesh_max(m_idx, s)
        order = np.lexsort((m, -best))[:k]
        m, best = m[order], best[order]
        if fallback_unit == "captions" and len(m):
            sel = np.isin(m_idx, m)
            cap_m, cap_s = m_idx[sel], s[sel]
            top = np.lexsort((cap_m, -cap_s))[:k]
            keep = np.isin(m, cap_m[top])
            m, best = m[keep], best[keep]
        return Stage1Result(m.astype(np.int32), best.astype(np.float32), True, time.perf_counter() - t0)

    def close(self) -> None:
        self.index = None
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

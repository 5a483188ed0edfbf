"""mesh_id -> mesh code for a sync: the base's ids memory-mapped with their sorted order, then the meshes new
since the base.

A sync of a small commit looks up a handful of ids against a base of millions. Building Arrow's hash set
over every base id (``pc.index_in``) costs about 0.3 s per million ids each time; a binary search over the
ids' sorted order (written with the base, ``mesh_sort``) touches about 20 of them per lookup. Neither Arrow
nor NumPy offers a search over a sorted string array, hence the small bisection here; a batch with many
distinct ids still goes through ``pc.index_in``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.ipc as ipc

BISECT_MAX = 2048  # distinct ids up to which a lookup bisects instead of hashing every base id


def read_ids(path: Path) -> pa.StringArray:
    """The mesh ids of an index's ``meshes-<g>.arrow``, memory-mapped (one chunk: no copy)."""
    col = ipc.open_file(pa.memory_map(str(path))).read_all().column(0)
    return col.chunk(0) if col.num_chunks == 1 else col.combine_chunks()


def sorted_order(ids: pa.Array) -> np.ndarray:
    """The permutation that sorts ``ids`` (stored with the base as ``mesh_sort``)."""
    return pc.sort_indices(ids).to_numpy().astype(np.int32)


class MeshLookup:
    """Codes of mesh ids: ``0..len(base)-1`` for the base's ids, then ``new`` (grown by :meth:`codes`)."""

    def __init__(self, base: pa.StringArray, order: np.ndarray, new: list[str]) -> None:
        self.base, self.order = base, order
        self.new = list(new)
        self._extra = {m: len(base) + i for i, m in enumerate(self.new)}

    def _find(self, m: str) -> int:
        lo, hi = 0, len(self.order)
        while lo < hi:
            mid = (lo + hi) // 2
            if self.base[int(self.order[mid])].as_py() < m:
                lo = mid + 1
            else:
                hi = mid
        if lo < len(self.order) and self.base[int(self.order[lo])].as_py() == m:
            return int(self.order[lo])
        return -1

    def base_codes(self, ids: pa.Array) -> np.ndarray:
        """Base code of every id (-1 for an id the base lacks)."""
        enc = pc.dictionary_encode(ids)
        values = enc.dictionary
        if len(values) <= BISECT_MAX:
            local = np.array([self._find(m) for m in values.to_pylist()], np.int64)
        else:
            local = pc.index_in(values, value_set=self.base).fill_null(-1).to_numpy().astype(np.int64)
        return local[enc.indices.to_numpy(zero_copy_only=False)] if len(ids) else np.zeros(0, np.int64)

    def codes(self, ids: pa.Array) -> np.ndarray:
        """Code of every id; an id seen nowhere yet gets the next new code."""
        out = self.base_codes(ids)
        for i in np.flatnonzero(out < 0):
            m = ids[int(i)].as_py()
            c = self._extra.get(m)
            if c is None:
                c = self._extra[m] = len(self.base) + len(self.new)
                self.new.append(m)
            out[i] = c
        return out

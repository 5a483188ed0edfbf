"""The query path's embedding cache, kept up to date from the Delta log instead of rebuilt.

Under ``STORE/_cache/query/<kind>-<key>/`` (``key``: the embedding fingerprint, the SQL and the layout,
not the store's files) the cache holds Arrow IPC *segments*, memory-mapped on open. Each segment holds the
rows (latest per ``(mesh_id, view_index)``, at the run's fingerprint) of the Delta data files it was built
from, with ``mesh_id`` dictionary-encoded, plus a small ``mesh_idx`` file for the active-mesh list it was
last numbered against. On open, the Delta table's current files are compared with the files the segments
cover: only the added files are read (one new segment); segments whose files were removed (compaction)
are dropped and their still-current files re-read; superseded rows (a ``--force`` re-run) are cut out of
the older segments; ``mesh_idx`` is renumbered through the dictionaries when the active meshes changed.
Rows of meshes that became inactive are cut out and remembered, and their reactivation rebuilds the cache.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.dataset as ds

MANIFEST = "manifest.json"
#: segments are merged into one when there are more than this many
MAX_SEGMENTS = 32
KEY = ["mesh_id", "view_index"]


class SegmentCache:
    """One cached table (``kind``: caption or view) of one store, for one fingerprint and layout."""

    def __init__(self, directory: Path, vector_columns, layout=None) -> None:
        self.dir = directory
        self.layout = layout  # (mesh_idx, embedding) -> (mesh_idx, e0..e7); None keeps ``embedding``
        self.vector_columns = vector_columns
        self.stats = {"read_files": 0, "new_segments": 0, "rewritten_segments": 0, "renumbered": 0}

    # ------------------------------------------------------------------ manifest
    def _manifest(self) -> dict:
        try:
            return json.loads((self.dir / MANIFEST).read_text())
        except (OSError, ValueError):
            return {"segments": [], "excluded": [], "next": 0}

    def _write_manifest(self, man: dict) -> None:
        _atomic_bytes(self.dir / MANIFEST, json.dumps(man).encode())

    # ------------------------------------------------------------------ open
    def load(
        self, files: list[tuple[str, Path]], schema: pa.Schema, fp: str, active_ids: pa.Array
    ) -> pa.Table:
        """The cached table for the Delta ``files`` ((name, path)) numbered against ``active_ids`` (sorted)."""
        self.dir.mkdir(parents=True, exist_ok=True)
        man = self._manifest()
        if man["excluded"] and pc.any(pc.is_in(active_ids, value_set=pa.array(man["excluded"]))).as_py():
            man = {"segments": [], "excluded": [], "next": man["next"]}  # a mesh came back: rebuild
        current = {name: path for name, path in files}
        kept = [s for s in man["segments"] if set(s["sources"]) <= current.keys()]
        covered = {name for s in kept for name in s["sources"]}
        added = [name for name in current if name not in covered]
        segments = {s["file"]: self._read(s["file"]) for s in kept}
        if added:
            new = self._build(ds.dataset([str(current[n]) for n in added], schema=schema), fp)
            self.stats["read_files"] += len(added)
            new = self._supersede(man, kept, segments, new)
            if new.num_rows:
                name = f"seg-{man['next']:06d}.arrow"
                man["next"] += 1
                self._write_segment(name, new)
                segments[name] = self._read(name)
                kept.append({"file": name, "sources": added, "sig": None})
                self.stats["new_segments"] += 1
            else:  # files without rows at this fingerprint are covered all the same
                kept.append({"file": None, "sources": added, "sig": None})
        sig = _signature(active_ids)
        parts = []
        for s in kept:
            if s["file"] is None:
                continue
            idx = self._mesh_idx(man, s, segments, active_ids, sig)
            seg = segments[s["file"]]
            if seg.num_rows:
                parts.append(self._output(seg, idx))
        if len([s for s in kept if s["file"]]) > MAX_SEGMENTS:
            kept = self._merge(man, kept, segments)
        for f in {s["file"] for s in man["segments"]} - {s["file"] for s in kept}:
            if f:
                (self.dir / f).unlink(missing_ok=True)
                (self.dir / _idx_name(f)).unlink(missing_ok=True)
        man["segments"] = kept
        self._write_manifest(man)
        if not parts:
            return self._empty()
        return pa.concat_tables(parts)

    def _output(self, seg: pa.Table, idx: pa.Array) -> pa.Table:
        cols = {"mesh_idx": idx, "view_index": seg.column("view_index")}
        for c in self.vector_columns(seg):
            cols[c] = seg.column(c)
        return pa.table(cols).replace_schema_metadata(seg.schema.metadata)

    def _empty(self) -> pa.Table:
        return pa.table({"mesh_idx": pa.array([], pa.int32()), "view_index": pa.array([], pa.int16())})

    # ------------------------------------------------------------------ building
    def _build(self, source: ds.Dataset, fp: str) -> pa.Table:
        """Rows of ``source`` at ``fp``, latest per key, in the cache's layout, ``mesh_id`` dictionary-encoded."""
        from pipeline.store import latest_rows

        t = source.to_table(
            columns=["mesh_id", "view_index", "run_id", "embedding"], filter=pc.field("fingerprint") == fp
        )
        t = latest_rows(t, KEY)
        return self._shape(t)

    def _shape(self, t: pa.Table) -> pa.Table:
        base = {
            "mesh_id": pc.dictionary_encode(t.column("mesh_id").combine_chunks()),
            "view_index": t.column("view_index").combine_chunks(),
            "run_id": t.column("run_id").combine_chunks(),
        }
        if self.layout is None:
            return pa.table({**base, "embedding": t.column("embedding").combine_chunks()})
        zero = pa.array(np.zeros(t.num_rows, np.int32))
        sliced = self.layout(pa.table({"mesh_idx": zero, "embedding": t.column("embedding")}))
        cols = {**base, **{c: sliced.column(c) for c in sliced.column_names if c != "mesh_idx"}}
        return pa.table(cols).replace_schema_metadata(sliced.schema.metadata)

    def _supersede(self, man: dict, kept: list[dict], segments: dict, new: pa.Table) -> pa.Table:
        """Cut rows of older segments that ``new`` supersedes (or drop new rows an older one beats)."""
        if not new.num_rows:
            return new
        new_ids = pc.unique(new.column("mesh_id").combine_chunks().dictionary_decode())
        new_keys = {
            (m, v): r
            for m, v, r in zip(
                new.column("mesh_id").to_pylist(),
                new.column("view_index").to_pylist(),
                new.column("run_id").to_pylist(),
                strict=True,
            )
        }
        beaten: set = set()
        for s in kept:
            if s["file"] is None:
                continue
            seg = segments[s["file"]]
            hit = _rows_of(seg, new_ids)
            if hit is None:
                continue
            rows = np.flatnonzero(hit)
            sub = seg.take(rows).select(["mesh_id", "view_index", "run_id"]).to_pylist()
            drop = []
            for i, r in zip(rows, sub, strict=True):
                k = (r["mesh_id"], r["view_index"])
                if k in new_keys:
                    if new_keys[k] >= r["run_id"]:
                        drop.append(i)
                    else:
                        beaten.add(k)
            if drop:
                keep = np.ones(seg.num_rows, bool)
                keep[drop] = False
                self._write_segment(s["file"], seg.filter(pa.array(keep)))
                segments[s["file"]] = self._read(s["file"])
                s["sig"] = None
                self.stats["rewritten_segments"] += 1
        if beaten:
            keep = [
                (m, v) not in beaten
                for m, v in zip(
                    new.column("mesh_id").to_pylist(), new.column("view_index").to_pylist(), strict=True
                )
            ]
            new = new.filter(pa.array(keep))
        return new

    def _mesh_idx(self, man: dict, s: dict, segments: dict, active_ids: pa.Array, sig: str) -> pa.Array:
        """``mesh_idx`` of a segment's rows (renumbered through its dictionary when the meshes changed);
        rows of inactive meshes are cut out of the segment for good."""
        path = self.dir / _idx_name(s["file"])
        if s.get("sig") == sig and path.exists():
            return _read_ipc(path).column("mesh_idx")
        seg = segments[s["file"]]
        col = seg.column("mesh_id")
        out, done = [], {}
        for chunk in col.chunks:
            key = _identity(chunk.dictionary)  # the chunks of one IPC file share their dictionary
            if key not in done:
                done[key] = pc.index_in(chunk.dictionary, value_set=active_ids)
            out.append(done[key].take(chunk.indices))
        idx = pa.chunked_array(out, pa.int32()) if out else pa.chunked_array([], pa.int32())
        if idx.null_count:
            inactive = pc.unique(pc.filter(_decoded_ids(seg), pc.is_null(idx))).to_pylist()
            man["excluded"] = sorted(set(man["excluded"]) | set(inactive))
            keep = pc.is_valid(idx)
            self._write_segment(s["file"], seg.filter(keep))
            segments[s["file"]] = self._read(s["file"])
            idx = pc.filter(idx, keep)
            self.stats["rewritten_segments"] += 1
        _write_ipc(path, pa.table({"mesh_idx": idx.cast(pa.int32())}))
        s["sig"] = sig
        self.stats["renumbered"] += 1
        return _read_ipc(path).column("mesh_idx")

    def _merge(self, man: dict, kept: list[dict], segments: dict) -> list[dict]:
        live = [s for s in kept if s["file"]]
        merged = pa.concat_tables([segments[s["file"]] for s in live]).unify_dictionaries()
        name = f"seg-{man['next']:06d}.arrow"
        man["next"] += 1
        self._write_segment(name, merged)
        sources = [n for s in kept for n in s["sources"]]
        return [{"file": name, "sources": sources, "sig": None}]

    # ------------------------------------------------------------------ files
    def _write_segment(self, name: str, table: pa.Table) -> None:
        table = table.unify_dictionaries() if table.num_rows else table
        _write_ipc(self.dir / name, table)

    def _read(self, name: str) -> pa.Table:
        return _read_ipc(self.dir / name)


def _signature(ids: pa.Array) -> str:
    """Hash of a string array's contents (its offsets and bytes), without Python strings."""
    ids = pa.array(ids.to_pylist(), pa.string()) if ids.offset else ids  # buffers start at the array
    h = hashlib.sha1(str(len(ids)).encode())
    for buf in ids.buffers()[1:]:
        if buf is not None:
            h.update(memoryview(buf))
    return h.hexdigest()


def _identity(arr: pa.Array) -> tuple:
    """Identity of an array's memory (equal for chunks that share one dictionary)."""
    return (len(arr), arr.offset, *(b.address if b is not None else 0 for b in arr.buffers()))


def _rows_of(seg: pa.Table, ids: pa.Array) -> np.ndarray | None:
    """Boolean mask of the segment's rows whose ``mesh_id`` is in ``ids`` (``None`` when no row is),
    computed on the dictionaries: no per-row string work."""
    masks, any_hit, done = [], False, {}
    for chunk in seg.column("mesh_id").chunks:
        key = _identity(chunk.dictionary)
        if key not in done:
            done[key] = pc.is_in(chunk.dictionary, value_set=ids)
        in_dict = done[key]
        if not pc.any(in_dict).as_py():
            masks.append(np.zeros(len(chunk), bool))
            continue
        any_hit = True
        masks.append(in_dict.to_numpy(zero_copy_only=False)[chunk.indices.to_numpy(zero_copy_only=False)])
    return np.concatenate(masks) if any_hit else None


def _decoded_ids(seg: pa.Table) -> pa.Array:
    col = seg.column("mesh_id")
    return pa.chunked_array([c.dictionary_decode() for c in col.chunks], pa.string())


def _idx_name(segment: str) -> str:
    return segment.replace("seg-", "idx-")


def _read_ipc(path: Path) -> pa.Table:
    import pyarrow.ipc as ipc

    return ipc.open_file(pa.memory_map(str(path), "r")).read_all()


def _write_ipc(path: Path, table: pa.Table) -> None:
    """Write via a temp name + rename (readers of the old file keep their mapping)."""
    import pyarrow.ipc as ipc

    tmp = path.with_name(f"{path.name}.{os.getpid()}.partial")
    try:
        with pa.OSFile(str(tmp), "wb") as sink, ipc.new_file(sink, table.schema) as writer:
            writer.write_table(table, max_chunksize=65536)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _atomic_bytes(path: Path, data: bytes) -> None:
    tmp = path.with_name(f"{path.name}.{os.getpid()}.partial")
    tmp.write_bytes(data)
    os.replace(tmp, path)

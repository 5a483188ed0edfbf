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
    """Every relation of :func:`connect` except the views: name -> Arrow dataset or (empty) table."""
    import pyarrow.dataset as ds

    out: dict[str, object] = {}
    for table, schema in schemas.TABLES.items():
        d = store.dataset(table)
        out[relation_name(table)] = d if d is not None else schema.empty_table()
    for table in schemas.EMBEDDING_TABLES:
        files: list[str] = []
        for dataset in store.datasets(table):
            d = store.dataset(dataset)
            if d is not None:
                out[relation_name(dataset)] = d
                files.extend(str(p) for p in store.parts(dataset))
        schema = any_encoder_schema()
        fs = getattr(store, "filesystem", None)  # set for stores read through a pyarrow filesystem
        out[relation_name(table)] = (
            ds.dataset(files, format="parquet", schema=schema, filesystem=fs)
            if files
            else schema.empty_table()
        )
    return out


class RemoteStore:
    """Read-only view of a store copied to object storage (``s3://``, ``gs://``, ``abfs://``, ``hdfs://``,
    ``file://``), read through a pyarrow filesystem: the commit log names the parts, as in :class:`Store`.

    Offers what :func:`connect` needs (``datasets``, ``parts``, ``dataset``); writing needs a local store.
    """

    def __init__(self, filesystem, root: str, parts: dict[str, list[str]]):
        self.filesystem, self.root, self._parts = filesystem, root.rstrip("/"), parts

    @classmethod
    def open(cls, uri: str, filesystem=None) -> RemoteStore:
        """Open the store at ``uri`` (credentials come from the usual environment of each filesystem)."""
        import json

        from pyarrow import fs

        from pipeline.store import LOG_DIR, STORE_MARKER, StoreError

        if filesystem is None:
            filesystem, root = fs.FileSystem.from_uri(uri)
        else:
            root = uri
        if filesystem.get_file_info(f"{root}/{STORE_MARKER}").type == fs.FileType.NotFound:
            raise StoreError(f"no OSCAR store at {uri} (no {STORE_MARKER})")
        entries = filesystem.get_file_info(fs.FileSelector(f"{root}/{LOG_DIR}", allow_not_found=True))
        parts: dict[str, list[str]] = {}
        for path in sorted(e.path for e in entries if e.path.endswith(".json")):
            with filesystem.open_input_stream(path) as f:
                entry = json.loads(f.read())
            for dataset, gone in entry.get("removes", {}).items():
                parts[dataset] = [p for p in parts.get(dataset, []) if p not in set(gone)]
            for dataset, added in entry.get("adds", {}).items():
                parts.setdefault(dataset, []).extend(added)
        return cls(filesystem, root, parts)

    def datasets(self, table: str) -> list[str]:
        if table in schemas.EMBEDDING_TABLES:
            return sorted(d for d in self._parts if d.startswith(table + "/") and self._parts[d])
        return [table] if self._parts.get(table) else []

    def parts(self, dataset: str) -> list[str]:
        return [f"{self.root}/{p}" for p in self._parts.get(dataset, [])]

    def dataset(self, dataset: str):
        import pyarrow.dataset as ds

        files = self.parts(dataset)
        if not files:
            return None
        table = dataset.split("/", 1)[0]
        schema = schemas.TABLES.get(table) if table in schemas.TABLES else None
        return ds.dataset(files, format="parquet", schema=schema, filesystem=self.filesystem)


def open_store(location: str):
    """A local :class:`Store` (read-only) for a path, a :class:`RemoteStore` for a URI with a scheme."""
    if "://" in location:
        return RemoteStore.open(location)
    return Store.open(location)


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

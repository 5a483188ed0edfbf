"""DuckDB access to a store: committed parts registered as Arrow datasets, SQL from ``sql/`` files.

Paths and user text never reach SQL as text: tables are registered objects and values are bound
parameters.
"""

from __future__ import annotations

from functools import cache
from pathlib import Path

from pipeline.store import Store

SQL_DIR = Path(__file__).resolve().parent.parent / "sql"


@cache
def load_sql(name: str) -> str:
    """Text of ``sql/<name>.sql`` (``name`` may include a sub-folder, e.g. ``audit/short_captions``)."""
    path = SQL_DIR / f"{name}.sql"
    if not path.is_file():
        raise FileNotFoundError(f"no SQL file {path}")
    return path.read_text()


def relation_name(dataset: str) -> str:
    """DuckDB name of a dataset: ``views`` -> ``views_all``; ``text_embeddings/x-y`` -> ``text_embeddings__x_y``."""
    if "/" in dataset:
        table, part = dataset.split("/", 1)
        return f"{table}__" + "".join(c if c.isalnum() else "_" for c in part)
    return f"{dataset}_all"


def connect(store: Store, database: str = ":memory:"):
    """A DuckDB connection with every committed dataset registered (``<table>_all``, one per embedding
    encoder ``<table>__<encoder_slug>``)."""
    import duckdb

    con = duckdb.connect(database)
    for table in ("meshes", "views", "captions", "errors", "runs", "text_embeddings", "image_embeddings"):
        for dataset in store.datasets(table):
            d = store.dataset(dataset)
            if d is not None:
                con.register(relation_name(dataset), d)
    return con

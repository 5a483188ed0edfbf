"""The analysts' SQL surface is read-only and confined to the store.

Two layers (see docs/analysts.md, "Security model"):

1. DuckDB itself: after the store's relations are registered (as Arrow datasets, read by pyarrow, not by
   DuckDB's file system), :func:`confine` sets ``enable_external_access = false`` and
   ``lock_configuration = true``. DuckDB then opens no file, URL or extension: ``read_csv('/etc/passwd')``,
   ``read_parquet``, ``ATTACH``, ``INSTALL``/``LOAD``, ``EXPORT DATABASE`` and ``COPY ... TO`` fail, and no
   setting can be changed back. The one exception is the export directory the analyst names
   (``--export-dir``), added to ``allowed_directories``: ``COPY ... TO`` may write there, and only there.
2. Each statement is checked before it runs (:func:`check_statement`), so the refusals read as one clear
   message instead of DuckDB's generic permission error, and statements that are harmless to the store but
   mean "change the session" (``SET threads``, ``ATTACH``) are refused even where DuckDB would allow them.

The store's files can never be written from SQL: the export directory may not be inside the store, nor
contain it.
"""

from __future__ import annotations

import re
from pathlib import Path

_VARIABLE_SET = re.compile(r"^\s*(SET|RESET)\s+VARIABLE\b", re.IGNORECASE)
_COMMENTS = re.compile(r"(--[^\n]*\n)|(/\*.*?\*/)", re.DOTALL)
_SECRET = re.compile(r"^\s*CREATE\s+(OR\s+REPLACE\s+)?(PERSISTENT\s+|TEMPORARY\s+)?SECRET\b", re.IGNORECASE)
_IMPORT = re.compile(r"^\s*IMPORT\s+DATABASE\b", re.IGNORECASE)
HINT = "the analysts' SQL surface is read-only (see docs/analysts.md)"


class RefusedStatement(ValueError):
    """A statement the analysts' surface does not run (it would leave the store's read-only view)."""


def check_export_dir(export_dir: str | Path, store_root: str | Path | None) -> Path:
    """The resolved export directory (created if missing); refuses one inside the store or containing it."""
    out = Path(export_dir).expanduser().resolve()
    if store_root is not None and "://" not in str(store_root):
        store = Path(store_root).resolve()
        if out == store or store in out.parents or out in store.parents:
            raise ValueError(
                f"--export-dir {export_dir} overlaps the store {store}: choose a folder outside it"
            )
    if out.exists() and not out.is_dir():
        raise ValueError(f"--export-dir {export_dir} is not a directory")
    out.mkdir(parents=True, exist_ok=True)
    return out


def confine(con, export_dir: Path | None = None) -> None:
    """Lock ``con`` down: no file, URL or extension access except writes under ``export_dir``.

    Call it after every relation and view is registered (registration needs nothing from DuckDB's file
    system; Arrow datasets are scanned by pyarrow); nothing can loosen these settings afterwards.
    """
    import atexit
    import shutil
    import tempfile

    # spill files go to a private folder, not to DuckDB's default ``./.tmp`` (which could be in the store)
    spill = tempfile.mkdtemp(prefix="oscar-sql-spill-")
    atexit.register(shutil.rmtree, spill, ignore_errors=True)
    con.execute("SET temp_directory = ?", [spill])
    con.execute("SET allowed_directories = ?", [[str(export_dir) + "/"] if export_dir else []])
    con.execute("SET enable_external_access = false")
    con.execute("SET autoinstall_known_extensions = false")
    con.execute("SET autoload_known_extensions = false")
    con.execute("SET lock_configuration = true")


def check_statement(statement) -> None:
    """Raise :class:`RefusedStatement` for a statement that would leave the read-only surface."""
    from duckdb import StatementType

    kind = statement.type
    text = _COMMENTS.sub(" ", statement.query).strip()
    head = text.split(None, 1)[0].upper() if text else ""
    if kind in (StatementType.ATTACH, StatementType.DETACH):
        raise RefusedStatement(f"{head} refused: {HINT}; other databases cannot be attached")
    if kind == StatementType.LOAD:
        raise RefusedStatement(f"{head} refused: {HINT}; extensions cannot be installed or loaded")
    if kind == StatementType.SET and not _VARIABLE_SET.match(text):
        raise RefusedStatement(
            f"{head} refused: {HINT}, its settings are fixed; "
            "use SET VARIABLE name = value (or --set) for audit thresholds"
        )
    if kind == StatementType.EXPORT or _IMPORT.match(text):
        raise RefusedStatement(f"{head} DATABASE refused: {HINT}; use --export-duckdb OUT for a copy")
    if _SECRET.match(text):
        raise RefusedStatement(f"CREATE SECRET refused: {HINT}; no remote storage is reachable from SQL")


def export_dirs(con) -> list[str]:
    """The directories ``COPY ... TO`` may write to on a confined connection (the export directory)."""
    try:
        dirs = con.execute("SELECT current_setting('allowed_directories')").fetchone()[0] or []
    except Exception:  # not a DuckDB connection with that setting
        return []
    return [d.rstrip("/") for d in dirs if "oscar-sql-spill-" not in d]


def explain_permission_error(exc: Exception, con=None) -> RefusedStatement:
    """A one-line :class:`RefusedStatement` for DuckDB's permission and locked-configuration errors."""
    first = (str(exc).splitlines() or [type(exc).__name__])[0]
    dirs = export_dirs(con) if con is not None else []
    where = f"writes only under --export-dir {dirs[0]}" if dirs else "needs --export-dir DIR"
    reason = first.split(": ", 1)[-1].replace(" - file system operations are disabled by configuration", "")
    return RefusedStatement(
        f"refused: {reason}: SQL here reads the store's tables only and COPY ... TO {where} "
        "(docs/analysts.md)"
    )


def is_permission_error(exc: Exception) -> bool:
    """True for DuckDB errors raised by the confinement (file access off, configuration locked)."""
    import duckdb

    if isinstance(exc, duckdb.PermissionException):
        return True
    text = str(exc)
    return "configuration has been locked" in text or "disabled by configuration" in text

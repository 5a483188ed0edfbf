"""Running SQL against a store: statements, files and audits, with results printed in one format."""

from __future__ import annotations

import re
import sys
from dataclasses import dataclass
from typing import TextIO

from pipeline.sql.output import render

#: statement results that only report success (printed as nothing)
_STATUS_COLUMNS = ({"Count"}, {"Success"})
_VARIABLE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


@dataclass
class Printer:
    """Where and how results go."""

    fmt: str = "table"
    max_width: int = 60
    stream: TextIO | None = None  # None: sys.stdout at the time of printing

    @property
    def out(self) -> TextIO:
        return self.stream or sys.stdout

    def show(self, columns: list[str], rows: list[tuple], title: str | None = None) -> None:
        if title and self.fmt == "table":
            print(f"-- {title}", file=self.out)
        print(render(columns, rows, self.fmt, self.max_width), file=self.out)


def open_store_connection(store_path: str, export_dir: str | None = None):
    """A confined DuckDB connection over the committed state of the store at ``store_path`` (read-only;
    ``COPY ... TO`` only under ``export_dir``)."""
    from pipeline.db import connect
    from pipeline.sql.confine import check_export_dir, confine
    from pipeline.store import Store

    store = Store.open(store_path)
    out = check_export_dir(export_dir, store.root) if export_dir else None
    con = connect(store)
    confine(con, out)
    return con


def set_variables(con, values: dict[str, str]) -> None:
    """``SET VARIABLE name = value`` for each item (values bound, names checked)."""
    for name, raw in values.items():
        if not _VARIABLE.match(name):
            raise ValueError(f"bad variable name {name!r}")
        con.execute(f"SET VARIABLE {name} = ?", [_parse_value(raw)])


def _parse_value(raw: str) -> object:
    for kind in (int, float):
        try:
            return kind(raw)
        except ValueError:
            pass
    return raw


def fetch(con, sql: str, params: list | None = None) -> tuple[list[str], list[tuple]]:
    """Run one statement (``params`` bound); return its column names and rows."""
    rel = con.sql(sql, params=params)  # None for statements without a result set
    if rel is None:
        return [], []
    table = rel.to_arrow_table()  # Arrow, not fetchall(): time zones convert without pytz
    return table.column_names, list(zip(*(c.to_pylist() for c in table.columns), strict=True))


def run_sql(con, sql: str, printer: Printer) -> int:
    """Run every statement of ``sql`` in order, printing each result set; return the rows printed.

    Statements that would leave the read-only surface are refused (:mod:`pipeline.sql.confine`)."""
    import duckdb

    from pipeline.sql.confine import check_statement, explain_permission_error, is_permission_error

    total = 0
    for statement in duckdb.extract_statements(sql):
        check_statement(statement)
        try:
            columns, rows = fetch(con, statement.query)
        except duckdb.Error as exc:
            if is_permission_error(exc):
                raise explain_permission_error(exc, con) from None
            raise
        if not columns or (set(columns) in _STATUS_COLUMNS and statement.type.name != "SELECT"):
            continue
        printer.show(columns, rows)
        total += len(rows)
    return total


def run_audit(con, name: str) -> tuple[list[str], list[tuple]]:
    """Columns and offending rows of the audit ``sql/audit/<name>.sql``."""
    from pipeline.db import audit_names, load_sql

    if name not in audit_names():
        raise ValueError(f"no audit {name!r}; audits: {', '.join(audit_names())}")
    return fetch(con, load_sql(f"audit/{name}"))


def run_audits(con, names: list[str], printer: Printer) -> dict[str, int]:
    """Run audits, print each one's offending rows; return rows found per audit."""
    found: dict[str, int] = {}
    for name in names:
        columns, rows = run_audit(con, name)
        found[name] = len(rows)
        printer.show(columns, rows, title=f"audit {name}: {len(rows)} offending row(s)")
    return found

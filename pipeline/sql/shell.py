"""A small interactive SQL shell (used when the ``duckdb`` CLI is not wanted or not installed).

Statements end with ``;`` and may span lines; dot commands (``.help``) control the shell. Reads from a
terminal with line editing, or from a pipe (``echo "SELECT 1;" | python -m pipeline.sql STORE``).
"""

from __future__ import annotations

import sys
from typing import TextIO

from pipeline.sql.output import FORMATS
from pipeline.sql.session import Printer, fetch, run_audits, run_sql, set_variables

HELP = """\
Statements end with ';'. Dot commands:
  .tables              relations and views, with what each holds
  .describe NAME       columns of a table or view, with types and comments
  .audits              the ready audits of sql/audit/
  .audit NAME|all      run an audit (or all of them)
  .set NAME VALUE      set a DuckDB variable (audit thresholds, e.g. audit_min_caption_chars)
  .mode FORMAT         output format: table, csv, json, markdown
  .width N             cut table cells at N characters (0: never)
  .help                this text
  .quit                leave (also Ctrl-D)"""

_TABLES_SQL = """
SELECT view_name AS name, CASE WHEN temporary THEN 'store table' ELSE 'view' END AS kind,
       coalesce(comment, '') AS about
FROM duckdb_views() WHERE NOT internal
ORDER BY kind, name
"""
_DESCRIBE_SQL = """
SELECT column_name, data_type, coalesce(comment, '') AS comment
FROM duckdb_columns() WHERE table_name = ? ORDER BY column_index
"""


class Shell:
    """The read-eval-print loop over one connection."""

    def __init__(self, con, printer: Printer, stdin: TextIO | None = None):
        self.con, self.printer = con, printer
        self.stdin = stdin or sys.stdin
        self.interactive = self.stdin.isatty()
        self._pending = ""  # statement text read so far

    def _lines(self):
        if self.interactive:
            try:
                import readline  # noqa: F401  (line editing and history for input())
            except ImportError:
                pass
            while True:
                try:
                    yield input("   ...> " if self._pending.strip() else "oscar> ")
                except EOFError:
                    print(file=self.printer.out)
                    return
        else:
            yield from (line.rstrip("\n") for line in self.stdin)

    def run(self) -> int:
        """Loop until EOF or ``.quit``; return 1 if any statement failed, else 0."""
        if self.interactive:
            print("OSCAR store shell (DuckDB). '.help' for commands, '.tables' for what is here.")
        status = 0
        for line in self._lines():
            if not self._pending and line.strip().startswith("."):
                if not self._command(line.strip()):
                    break
                continue
            self._pending += line + "\n"
            if self._pending.rstrip().endswith(";"):
                status |= self._execute()
        if self._pending.strip():
            status |= self._execute()
        return status

    def _execute(self) -> int:
        sql, self._pending = self._pending, ""
        try:
            run_sql(self.con, sql, self.printer)
        except Exception as exc:  # show the error, keep the session
            print(f"Error: {exc}", file=sys.stderr)
            return 1
        return 0

    def _command(self, line: str) -> bool:
        """Run a dot command; return False to leave the shell."""
        cmd, _, arg = line.partition(" ")
        arg = arg.strip()
        try:
            if cmd in (".quit", ".exit"):
                return False
            if cmd == ".help":
                print(HELP, file=self.printer.out)
            elif cmd == ".tables":
                self.printer.show(*fetch(self.con, _TABLES_SQL))
            elif cmd == ".describe" and arg:
                self.printer.show(*fetch(self.con, _DESCRIBE_SQL, [arg]))
            elif cmd == ".audits":
                from pipeline.db import audit_names

                print("\n".join(audit_names()), file=self.printer.out)
            elif cmd == ".audit" and arg:
                from pipeline.db import audit_names

                run_audits(self.con, audit_names() if arg == "all" else [arg], self.printer)
            elif cmd == ".set" and arg:
                name, _, value = arg.partition(" ")
                set_variables(self.con, {name: value.strip()})
            elif cmd == ".mode" and arg in FORMATS:
                self.printer.fmt = arg
            elif cmd == ".width" and arg.isdigit():
                self.printer.max_width = int(arg)
            else:
                print(f"unknown or incomplete command {line!r}; try .help", file=sys.stderr)
        except Exception as exc:
            print(f"Error: {exc}", file=sys.stderr)
        return True

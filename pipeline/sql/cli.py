"""``python -m pipeline.sql STORE [-c SQL | -f FILE | --audit NAME|all | --export-duckdb OUT | --init-script]``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipeline.cli_common import OneLineParser, non_negative_int
from pipeline.sql.output import FORMATS


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(
        prog="python -m pipeline.sql",
        description="SQL over an OSCAR store: every table and the views of sql/views/ are registered. "
        "Without -c/-f/--audit it opens an interactive shell (statements from stdin when piped).",
    )
    p.add_argument(
        "store",
        metavar="STORE",
        help="store directory, or a copy of one in object storage (s3://bucket/store, gs://..., file://...)",
    )
    what = p.add_mutually_exclusive_group()
    what.add_argument("-c", "--command", metavar="SQL", help="run SQL (one or more statements) and print")
    what.add_argument("-f", "--file", metavar="FILE", help="run the statements of a .sql file and print")
    what.add_argument(
        "--audit", metavar="NAME", action="append", help="run an audit of sql/audit/ (repeatable, or 'all')"
    )
    what.add_argument("--list-audits", action="store_true", help="list the audits and exit")
    what.add_argument(
        "--export-duckdb", metavar="OUT", help="write a DuckDB database file with every table and view"
    )
    what.add_argument(
        "--init-script",
        action="store_true",
        help="print DuckDB SQL that defines every table (over the committed parts) and view, "
        "for `duckdb -init FILE`",
    )
    what.add_argument(
        "--duckdb-cli",
        action="store_true",
        help="open the `duckdb` command-line shell (must be on PATH) instead of the built-in one",
    )
    p.add_argument("--format", default="table", choices=FORMATS, help="output format (default: %(default)s)")
    p.add_argument(
        "--max-width",
        type=non_negative_int,
        default=60,
        help="cut table/markdown cells at N characters (0: never)",
    )
    p.add_argument(
        "--set",
        metavar="NAME=VALUE",
        action="append",
        default=[],
        help="set a DuckDB variable first, e.g. audit_min_caption_chars=25 (repeatable)",
    )
    p.add_argument(
        "--export-dir",
        metavar="DIR",
        help="the one folder COPY ... TO may write to (created; must be outside the store); "
        "without it SQL cannot write files at all",
    )
    p.add_argument(
        "--as-of",
        metavar="VERSION|TIME",
        help="time travel: the store as it was right after version VERSION of its runs table (one "
        "commit per onboarding run; `python -m pipeline.fsck STORE --runs` lists them) or as the last run "
        "recorded by an ISO time left it (a time before the first run is an error)",
    )
    p.add_argument("--check", action="store_true", help="with --audit: exit 1 when any audit finds rows")
    p.add_argument("--force", action="store_true", help="with --export-duckdb: replace an existing file")
    return p


def _variables(items: list[str]) -> dict[str, str]:
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise ValueError(f"--set expects NAME=VALUE, got {item!r}")
        out[name.strip()] = value.strip()
    return out


def main(argv: list[str] | None = None) -> int:
    from pipeline.cli_common import reader_gone

    leases: list = []
    try:
        return _main(argv, leases)
    except BrokenPipeError:  # `... | head` closed the pipe: the reader has what it wanted
        return reader_gone()
    finally:
        for lease in leases:
            lease.release()


def _main(argv: list[str] | None, leases: list) -> int:
    args = build_parser().parse_args(argv)
    from pipeline.cli_common import fail
    from pipeline.db import RemoteStore, audit_names, open_store
    from pipeline.store import StoreError

    if args.list_audits:
        print("\n".join(audit_names()))
        return 0
    try:
        store = open_store(args.store, as_of=args.as_of)
    except (StoreError, OSError, ValueError) as exc:
        return fail(str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
    if (args.init_script or args.duckdb_cli) and isinstance(store, RemoteStore):
        return fail("--init-script and --duckdb-cli need a local store; use --export-duckdb for a remote one")
    if args.init_script:
        from pipeline.sql.export import init_script

        sys.stdout.write(init_script(store))
        return 0
    if args.export_duckdb:
        from pipeline.sql.export import export_duckdb

        root = _local_root(store)
        if root is not None and root.resolve() in Path(args.export_duckdb).resolve().parents:
            return fail(
                f"--export-duckdb {args.export_duckdb} is inside the store {root}: write it elsewhere"
            )
        try:
            out = export_duckdb(store, args.export_duckdb, overwrite=args.force)
        except OSError as exc:
            return fail(
                str(exc) if isinstance(exc, FileExistsError) else f"cannot write {args.export_duckdb}: {exc}"
            )
        print(f"wrote {out}: open it with `duckdb {out}` (tables <table>_all, views as in docs/analysts.md)")
        return 0
    if args.duckdb_cli:
        return _exec_duckdb_cli(store)

    import duckdb

    from pipeline.db import connect
    from pipeline.sql.confine import check_export_dir, confine
    from pipeline.sql.session import Printer, run_audits, run_sql, set_variables

    try:
        export_dir = check_export_dir(args.export_dir, _local_root(store)) if args.export_dir else None
    except (ValueError, OSError) as exc:
        return fail(str(exc))
    try:
        _hold_lease(store, leases)
        con = connect(store)
    except StoreError as exc:
        return fail(str(exc))
    except (OSError, ValueError, RuntimeError, duckdb.Error) as exc:  # a damaged or vanished store file
        return fail(f"cannot read the store {args.store}: {type(exc).__name__}: {str(exc).splitlines()[0]}")
    confine(con, export_dir)  # after every relation and view is registered
    printer = Printer(args.format, args.max_width)
    try:
        set_variables(con, _variables(args.set))
        if args.command is not None:
            run_sql(con, args.command, printer)
            return 0
        if args.file is not None:
            with open(args.file) as fh:
                run_sql(con, fh.read(), printer)
            return 0
        if args.audit:
            names = audit_names() if "all" in args.audit else args.audit
            found = run_audits(con, names, printer)
            return 1 if args.check and any(found.values()) else 0
    except BrokenPipeError:
        raise
    except (duckdb.Error, ValueError, OSError) as exc:
        return fail(str(exc).splitlines()[0] if str(exc) else type(exc).__name__, 1)

    from pipeline.sql.shell import Shell

    return Shell(con, printer).run()


def _local_root(store) -> Path | None:
    from pipeline.store import Store

    return store.root if isinstance(store, Store) else None


def _exec_duckdb_cli(store) -> int:
    import os
    import shutil
    import tempfile

    from pipeline.cli_common import fail
    from pipeline.sql.export import init_script

    binary = shutil.which("duckdb")
    if binary is None:
        return fail("no `duckdb` on PATH; drop --duckdb-cli to use the built-in shell")
    fd, path = tempfile.mkstemp(prefix="oscar-store-", suffix=".sql")
    with os.fdopen(fd, "w") as fh:
        fh.write(init_script(store))
    os.execv(binary, [binary, "-init", path])
    return 0  # not reached


def _hold_lease(store, leases: list) -> None:
    """Pin a local store to a consistent snapshot leased until the session ends (added to ``leases``):
    compaction spares what the session reads, however long it lasts (:mod:`pipeline.leases`)."""
    from pipeline.snapshot import pin_and_lease

    lease = pin_and_lease(store, "sql")
    if lease is not None:
        leases.append(lease)

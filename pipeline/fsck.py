"""``python -m pipeline.fsck STORE``: check a store's integrity and say how to repair what is wrong.

Checks, per Delta table: the log loads and its versions run without gaps; every data file it references
is present, has the size the log recorded, opens as Parquet and has the table's schema; keys are unique
among the latest rows; and across tables, that every embedded or captioned mesh has a ``meshes`` row and
the DuckDB views build. Files no commit names (left by killed writers) are listed, never deleted: a lost
log entry would make committed files look the same. Exit status 0 when clean, 1 when a problem was found.
"""

from __future__ import annotations

import argparse
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from pipeline import schemas
from pipeline.store import DELTA_LOG, Store, StoreError, table_of

_VERSION_FILE = re.compile(r"^(\d{20})\.json$")


@dataclass
class Report:
    problems: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def bad(self, text: str) -> None:
        self.problems.append(text)


def check_log(store: Store, dataset: str, report: Report) -> bool:
    """The ``_delta_log`` files: contiguous versions, each one non-empty JSON. Returns False if unusable."""
    import json

    log = store.path_of(dataset) / DELTA_LOG
    versions = sorted(int(m.group(1)) for p in log.iterdir() if (m := _VERSION_FILE.match(p.name)))
    checkpoints = sorted(log.glob("*.checkpoint.parquet"))
    first = 0 if not checkpoints else None
    if versions and first == 0 and versions[0] != 0:
        report.bad(f"{log}/{0:020d}.json is missing (table {dataset}): restore it from a backup")
        return False
    expected = list(range(versions[0], versions[-1] + 1)) if versions else []
    for v in sorted(set(expected) - set(versions)):
        report.bad(f"{log}/{v:020d}.json is missing (table {dataset}): restore it from a backup")
    for v in versions:
        path = log / f"{v:020d}.json"
        try:
            lines = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
            if not lines:
                raise ValueError("empty")
        except (OSError, ValueError) as exc:
            report.bad(f"{path} is damaged ({str(exc)[:60]}; table {dataset}): restore it from a backup")
    return not report.problems


def check_files(store: Store, dataset: str, report: Report) -> None:
    """Every referenced data file present, of the logged size, readable, with the expected schema."""
    expected = store.schema(dataset)
    for path, size in store.files(dataset):
        if not path.exists():
            report.bad(f"{path} is missing (table {dataset}): restore it from a backup")
            continue
        if path.stat().st_size != size:
            report.bad(
                f"{path} is {path.stat().st_size} bytes, the log says {size} (table {dataset}): restore it"
            )
            continue
        try:
            got = pq.read_schema(path)
            pq.ParquetFile(path).read_row_group(0, columns=[got.names[0]]) if got.names else None
        except (OSError, pa.ArrowException) as exc:
            report.bad(f"{path} is not readable Parquet ({str(exc)[:60]}; table {dataset}): restore it")
            continue
        if expected is not None:
            missing = [f.name for f in expected if f.name not in got.names]
            if missing:
                report.bad(
                    f"{path} lacks columns {', '.join(missing[:3])} (table {dataset}): it is not this "
                    "table's file; restore it from a backup"
                )


def check_orphans(store: Store, dataset: str, report: Report) -> None:
    referenced = {p.resolve() for p in store.parts(dataset)}
    base = store.path_of(dataset)
    orphans = [p for p in base.glob("*.parquet") if p.resolve() not in referenced]
    if orphans:
        report.notes.append(
            f"{dataset}: {len(orphans)} data file(s) no commit names (killed writers or files vacuum keeps "
            "for old snapshots); `python -m pipeline.compact STORE --remove-orphans` deletes unreferenced "
            "ones once they are older than the retention, but only after this check is clean"
        )


def check_keys(store: Store, dataset: str, report: Report) -> None:
    """No two rows of one run share a key (a duplicated commit or a corrupt file)."""
    key = list(schemas.KEYS.get(table_of(dataset), ()))
    if not key:
        return
    t = store.read(dataset, columns=[*key, "run_id"])
    n = t.group_by([*key, "run_id"], use_threads=False).aggregate([]).num_rows
    if n != t.num_rows:
        report.bad(
            f"table {dataset}: {t.num_rows - n} duplicate key row(s) within one run: "
            "`python -m pipeline.compact STORE` keeps one row per key"
        )


def check_views(store: Store, report: Report) -> None:
    """Cross-table consistency and the analysts' views."""
    import duckdb

    from pipeline.db import connect

    try:
        con = connect(store)
    except (RuntimeError, duckdb.Error, StoreError) as exc:
        report.bad(f"the SQL views do not build: {str(exc).splitlines()[0]}")
        return
    known = {r[0] for r in con.execute("SELECT DISTINCT mesh_id FROM meshes_all").fetchall()}
    for rel in ("views_all", "captions_all", "text_embeddings_all", "image_embeddings_all"):
        ids = {r[0] for r in con.execute(f"SELECT DISTINCT mesh_id FROM {rel}").fetchall()}  # noqa: S608
        stray = ids - known
        if stray:
            report.bad(
                f"{rel}: {len(stray)} mesh_id(s) without a meshes row (e.g. {min(stray)[:12]}): "
                "re-run onboarding on the library"
            )


def runs_versions(store: Store) -> list[str]:
    """A header, then ``version  recorded at (UTC)  run_id  status`` per commit of the runs table: the
    versions ``--as-of`` takes."""
    from datetime import datetime, timezone

    dt = store.delta("runs")
    if dt is None:
        return ["no runs recorded yet"]
    runs = store.read("runs", columns=["run_id", "status"]).to_pylist()
    status = {r["run_id"]: r["status"] for r in runs}
    rows = [f"{'version':>7}  {'recorded at (UTC)':<23}  {'run_id':<29}  status"]
    for h in sorted(dt.history(), key=lambda h: h["version"]):
        at = datetime.fromtimestamp(h["timestamp"] / 1000, tz=timezone.utc).strftime("%Y-%m-%d %H:%M:%S.%f")[
            :-3
        ]
        run_id = h.get("oscar_run_id") or ""
        what = status.get(run_id) or h["operation"].lower()
        rows.append(f"{h['version']:>7}  {at:<23}  {run_id:<29}  {what}")
    return rows


def fsck(path: str | Path) -> Report:
    """Check the store at ``path``; return what is wrong (problems) and what is merely untidy (notes)."""
    report = Report()
    store = Store.open(path)
    for dataset in _all_datasets_on_disk(store):
        if not check_log(store, dataset, report):
            continue
        try:
            store.delta(dataset)
        except StoreError as exc:
            report.bad(str(exc).split("; run ")[0])
            continue
        before = len(report.problems)
        check_files(store, dataset, report)
        check_orphans(store, dataset, report)
        if len(report.problems) == before:
            check_keys(store, dataset, report)
    if not report.problems:
        check_views(store, report)
    return report


def _all_datasets_on_disk(store: Store) -> list[str]:
    out = []
    for table in (*schemas.TABLES, *schemas.EMBEDDING_TABLES):
        base = store.root / table
        if (base / DELTA_LOG).is_dir():
            out.append(table)
        elif table in schemas.EMBEDDING_TABLES and base.is_dir():
            out.extend(f"{table}/{p.name}" for p in sorted(base.iterdir()) if (p / DELTA_LOG).is_dir())
    return out


def main(argv: list[str] | None = None) -> int:
    from pipeline.cli_common import fail

    p = argparse.ArgumentParser(prog="python -m pipeline.fsck", description=__doc__.splitlines()[0])
    p.add_argument("store", metavar="STORE")
    p.add_argument("--runs", action="store_true", help="also list the runs table's versions (for --as-of)")
    args = p.parse_args(argv)
    try:
        report = fsck(args.store)
    except StoreError as exc:
        return fail(str(exc))
    for line in report.problems:
        print(f"problem: {line}")
    for line in report.notes:
        print(f"note: {line}")
    if args.runs:
        print("\n".join(runs_versions(Store.open(args.store))))
    if report.problems:
        print(
            f"{len(report.problems)} problem(s). Restore the named files from a backup (or copy the store "
            "and re-run onboarding into a fresh one); nothing was changed."
        )
        return 1
    print(f"store {args.store}: ok")
    return 0


if __name__ == "__main__":
    sys.exit(main())

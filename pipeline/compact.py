"""``python -m pipeline.compact STORE``: compact every table, drop superseded rows, vacuum old files.

Per table: when some rows are superseded (same key as a later row: ``--force`` re-runs, retried meshes)
the table is rewritten with its latest rows (one Delta overwrite commit); otherwise Delta's ``optimize``
merges its small files; ``runs`` is committed last (rewritten with its own rows when it had nothing to
compact), since readers pin every table as of its newest commit. Once every table is compacted,
``vacuum`` deletes the files that the log marked as removed more than ``--retention-hours`` ago (default
7 days), except the files of every table version that a live reader lease holds (:mod:`pipeline.leases`:
the query service, open Retrievers, the SQL shell), whatever the retention; it says which leases held
files back, and removes expired leases. Vacuum only deletes files the log names as removed, never files
it merely does not know, and it runs only on tables whose files all check out. Runs under the store's
writer lock.
"""

from __future__ import annotations

import sys
from pathlib import Path

from pipeline import schemas
from pipeline.cli_common import OneLineParser, fail, float_range
from pipeline.store import Store, io_error_message, new_run_id, os_error_of, table_of

DEFAULT_RETENTION_HOURS = 7 * 24
#: a run compacts a table automatically once it has this many files under SMALL_FILE_BYTES
AUTO_COMPACT_FILES = 64
SMALL_FILE_BYTES = 16 * 1024 * 1024


def superseded(store: Store, dataset: str) -> int:
    """Number of rows of ``dataset`` that a later row with the same key replaces."""
    key = list(schemas.KEYS.get(table_of(dataset), ()))
    if not key:
        return 0
    t = store.read(dataset, columns=key)
    return t.num_rows - t.group_by(key, use_threads=False).aggregate([]).num_rows


def compact_dataset(store: Store, dataset: str, run_id: str) -> dict:
    """Compact one dataset; return ``{"files_before", "files_after", "rows", "dropped"}``."""
    before = len(store.files(dataset))
    dropped = superseded(store, dataset)
    if dropped:
        latest = store.read_latest(dataset)
        store.append(dataset, latest, run_id, mode="overwrite")
        rows = latest.num_rows
    else:
        dt = store.delta(dataset)
        if before > 1:
            dt.optimize.compact(writer_properties=_props(store, dataset))
        rows = store.read(dataset, columns=["run_id"]).num_rows
    store.refresh(dataset)  # reload at the new version
    return {
        "files_before": before,
        "files_after": len(store.files(dataset)),
        "rows": rows,
        "dropped": dropped,
    }


def seal(store: Store, before: dict[str, int | None], run_id: str) -> bool:
    """Commit ``runs`` last when compaction committed to other tables but not to it (one file, nothing
    superseded: a store's first run committed in batches, a run killed before its record): readers pin
    every table as of the newest ``runs`` commit (:mod:`pipeline.snapshot`), so they would otherwise stay
    on the versions compaction just tombstoned, and vacuum would delete the files every new reader opens.
    Rewrites ``runs`` with its own rows (one overwrite commit); returns whether it did."""
    after = store.versions()
    if after == before or after.get("runs") is None or after["runs"] != before.get("runs"):
        return False  # nothing compacted, no runs table, or runs was compacted (last) already
    store.append("runs", store.read("runs"), run_id, mode="overwrite")
    store.refresh("runs")
    return True


def vacuum_dataset(
    store: Store, dataset: str, retention_hours: float, orphans: bool = False, leases: list | None = None
) -> int:
    """Delete files the log removed more than ``retention_hours`` ago (with ``orphans``, also files no
    commit names that are that old: left by killed writers), sparing the files of the versions that
    ``leases`` (:class:`~pipeline.leases.LeaseInfo`) hold; return how many were deleted."""
    return vacuum_report(store, dataset, retention_hours, orphans, leases or [])[0]


def vacuum_report(
    store: Store, dataset: str, retention_hours: float, orphans: bool, leases: list
) -> tuple[int, int, list[str]]:
    """Vacuum ``dataset`` sparing the leased versions: (files deleted, files kept for leases, the
    leases that kept some)."""
    store.check_files(dataset)  # never act on a log whose files do not check out
    dt = store.delta(dataset)
    keep = sorted({v for lease in leases for v in lease.versions.get(dataset, ()) if v <= dt.version()})
    args = {"retention_hours": int(retention_hours), "enforce_retention_duration": False, "full": orphans}
    held, holders = 0, []
    if keep:
        spared = set(dt.vacuum(dry_run=True, **args)) - set(
            dt.vacuum(dry_run=True, keep_versions=keep, **args)
        )
        held = len(spared)
        if spared:
            holders = [lease.describe() for lease in leases if _needs(dt, dataset, lease, spared)]
    gone = dt.vacuum(dry_run=False, keep_versions=keep or None, **args)
    return len(gone), held, holders


def _needs(dt, dataset: str, lease, files: set[str]) -> bool:
    """Whether ``lease`` holds a version of ``dt`` that references one of ``files`` (relative paths)."""
    from deltalake import DeltaTable

    for v in lease.versions.get(dataset, ()):
        if v > dt.version():
            continue
        paths = DeltaTable(dt.table_uri, version=v).get_add_actions(flatten=True).column("path").to_pylist()
        if files.intersection(paths):
            return True
    return False


def auto_compact(store: Store, run_id: str, threshold: int = AUTO_COMPACT_FILES) -> list[str]:
    """Compact the datasets with more than ``threshold`` small files (no vacuum); return their names."""
    done = []
    for dataset in store.all_datasets():
        if store.small_files(dataset, SMALL_FILE_BYTES) > threshold:
            compact_dataset(store, dataset, run_id)
            done.append(dataset)
    return done


def _props(store: Store, dataset: str):
    """The store's Parquet settings for ``dataset``; for a blob table, row groups of one model's rows (the
    merged files are each sorted by model, so each model's rows stay together)."""
    from pipeline.store import BLOB_TABLES, model_group_rows, writer_properties

    if table_of(dataset) not in BLOB_TABLES:
        return writer_properties(dataset)
    return writer_properties(dataset, model_group_rows(store.read(dataset, columns=["mesh_id"]).column(0)))


def main(argv: list[str] | None = None) -> int:
    p = OneLineParser(prog="python -m pipeline.compact", description=__doc__.splitlines()[0])
    p.add_argument("store", metavar="STORE")
    p.add_argument(
        "--retention-hours",
        type=float_range(0.0),
        default=DEFAULT_RETENTION_HOURS,
        help="vacuum files removed longer ago than this (default: %(default)s = 7 days), except files "
        "that live reader leases still read (services, open Retrievers, sql sessions)",
    )
    p.add_argument("--no-vacuum", action="store_true", help="compact only; delete no files")
    p.add_argument(
        "--remove-orphans",
        action="store_true",
        help="also delete data files no commit names (left by killed writers) older than the retention; "
        "run `python -m pipeline.fsck STORE` first: a lost log entry makes committed files look orphaned",
    )
    args = p.parse_args(argv)
    from pipeline.leases import live_leases, remove_expired
    from pipeline.store import StoreError

    run_id = new_run_id()
    try:
        with Store.open(args.store, writable=True) as store:
            # every table first, runs last: a reader that leases after the vacuum below read the leases
            # then sees (and leases) the compacted versions (pipeline.snapshot.open_snapshot)
            before = store.versions()
            done = [(dataset, compact_dataset(store, dataset, run_id)) for dataset in store.all_datasets()]
            sealed = seal(store, before, run_id)
            for dataset, r in done:
                line = (
                    f"{dataset}: {r['files_before']} files -> {r['files_after']}, {r['rows']} rows "
                    f"({r['dropped']} superseded dropped)"
                )
                if sealed and dataset == "runs":
                    line += ", rewritten last so that readers see the compacted tables"
                if not args.no_vacuum:
                    leases = live_leases(store.root)  # read per table: the freshest view of the readers
                    n, held, holders = vacuum_report(
                        store, dataset, args.retention_hours, args.remove_orphans, leases
                    )
                    line += f", {n} old files vacuumed"
                    if held:
                        line += f", {held} kept for live readers: {', '.join(holders)}"
                print(line)
            if not args.no_vacuum:
                for lease in remove_expired(store.root):
                    print(f"expired reader lease {lease.describe()} ignored and removed")
    except StoreError as exc:
        return fail(str(exc))
    except Exception as exc:  # noqa: BLE001 - delta-rs reports a full disk as DeltaError "(os error 28)"
        err = os_error_of(exc)
        if err is None:
            raise
        return fail(io_error_message(err, Path(args.store), "commit"))
    return 0


if __name__ == "__main__":
    sys.exit(main())

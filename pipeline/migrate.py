"""``python -m pipeline.migrate OLD NEW``: convert a store of the old format (Parquet parts named by a
``_log`` of JSON commits, format 1) into a Delta Lake store, without re-rendering anything.

Each old commit becomes one Delta commit per dataset it added to, in commit order, so superseded rows
and the run history carry over unchanged. Removes (old compactions) are applied by replaying the log
into the final part list first. OLD is only read.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from pipeline import schemas
from pipeline.store import LEGACY_LOG_DIR, STORE_MARKER, Store, StoreError, table_of


def legacy_parts(root: Path) -> list[tuple[str, str, str]]:
    """(run_id, dataset, part path) of every committed part of an old store, in commit order."""
    marker = root / STORE_MARKER
    if not marker.exists() or json.loads(marker.read_text()).get("format_version") != 1:
        raise StoreError(f"{root} is not a store in the old Parquet+_log format (format_version 1)")
    log = root / LEGACY_LOG_DIR
    live: dict[str, list[tuple[str, str]]] = {}
    order: list[str] = []
    for entry in sorted(log.glob("*.json")):
        try:
            data = json.loads(entry.read_text())
        except ValueError:
            raise StoreError(f"{entry}: damaged log entry; nothing was converted") from None
        for dataset, gone in data.get("removes", {}).items():
            live[dataset] = [(r, p) for r, p in live.get(dataset, []) if p not in set(gone)]
        for dataset, parts in data.get("adds", {}).items():
            live.setdefault(dataset, []).extend((data.get("run_id", ""), p) for p in parts)
            order.extend(parts)
    rank = {p: i for i, p in enumerate(order)}
    out = [(run, dataset, p) for dataset, parts in live.items() for run, p in parts]
    return sorted(out, key=lambda x: rank[x[2]])


def migrate(old: str | Path, new: str | Path) -> dict[str, int]:
    """Write every committed row of the old store at ``old`` into a new Delta store at ``new``."""
    old, new = Path(old), Path(new)
    parts = legacy_parts(old)
    for _, _, rel in parts:
        if not (old / rel).is_file():
            raise StoreError(f"{old / rel} is missing: the old store is damaged; nothing was converted")
    rows: dict[str, int] = {}
    with Store.open(new, create=True) as store:
        if store.all_datasets():
            raise StoreError(f"{new} already holds tables: migrate into a new, empty directory")
        batch: dict[str, list[pa.Table]] = {}
        current = None
        for run_id, dataset, rel in parts + [(None, None, None)]:
            if run_id != current and batch:
                store.commit({d: pa.concat_tables(ts) for d, ts in batch.items()}, current or "migrated")
                batch = {}
            if dataset is None:
                break
            current = run_id
            t = pq.read_table(old / rel)
            if table_of(dataset) in schemas.TABLES:
                t = schemas.conform(t, schemas.TABLES[table_of(dataset)])
            batch.setdefault(dataset, []).append(t)
            rows[dataset] = rows.get(dataset, 0) + t.num_rows
    return rows


def write_legacy(root: str | Path, commits: list[tuple[str, dict[str, pa.Table]]]) -> None:
    """Write a store in the old format (the format-1 writer: parts + one ``_log`` entry per commit),
    kept so that tests can build the stores that ``migrate`` converts."""
    root = Path(root)
    (root / LEGACY_LOG_DIR).mkdir(parents=True, exist_ok=True)
    (root / STORE_MARKER).write_text(json.dumps({"format_version": 1}))
    for seq, (run_id, tables) in enumerate(commits, start=1):
        adds: dict[str, list[str]] = {}
        for n, (dataset, table) in enumerate(tables.items()):
            rel = f"{dataset}/part-{run_id}-{n:05d}.parquet"
            (root / dataset).mkdir(parents=True, exist_ok=True)
            pq.write_table(table, root / rel, compression="zstd")
            adds[dataset] = [rel]
        entry = {"seq": seq, "run_id": run_id, "adds": adds, "removes": {}}
        (root / LEGACY_LOG_DIR / f"{seq:012d}.json").write_text(json.dumps(entry))


def main(argv: list[str] | None = None) -> int:
    from pipeline.cli_common import fail

    p = argparse.ArgumentParser(prog="python -m pipeline.migrate", description=__doc__.splitlines()[0])
    p.add_argument("old", metavar="OLD", help="store in the old format (read only)")
    p.add_argument("new", metavar="NEW", help="new, empty directory for the Delta Lake store")
    args = p.parse_args(argv)
    try:
        rows = migrate(args.old, args.new)
    except (StoreError, OSError, pa.ArrowException) as exc:
        return fail(str(exc).splitlines()[0])
    for dataset, n in sorted(rows.items()):
        print(f"{dataset}: {n} rows")
    print(f"migrated {args.old} -> {args.new}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

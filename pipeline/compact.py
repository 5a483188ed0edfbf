"""``python -m pipeline.compact STORE``: merge each table's parts into one and drop superseded rows.

Superseded rows are those with the same key as a later row (``--force`` re-runs, retried meshes). Runs
under the store's writer lock, so it never races an onboarding run; readers keep working throughout
because the old parts stay valid until the commit that replaces them.
"""

from __future__ import annotations

import sys

from pipeline.cli_common import OneLineParser, fail


def main(argv: list[str] | None = None) -> int:
    p = OneLineParser(prog="python -m pipeline.compact", description=__doc__.splitlines()[0])
    p.add_argument("store", metavar="STORE")
    args = p.parse_args(argv)
    from pipeline.store import Store, StoreError

    try:
        with Store.open(args.store, writable=True) as store:
            before = {d: len(store.parts(d)) for d in list(store._snap.parts)}
            kept = store.compact()
    except StoreError as exc:
        return fail(str(exc))
    except OSError as exc:
        return fail(f"I/O error on the store or library: {type(exc).__name__}: {str(exc).splitlines()[0]}")
    for dataset, rows in sorted(kept.items()):
        print(f"{dataset}: {before.get(dataset, 0)} parts -> 1, {rows} rows")
    return 0


if __name__ == "__main__":
    sys.exit(main())

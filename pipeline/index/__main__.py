"""``python -m pipeline.index build|sync|status STORE``: the stage-1 index of a store's caption embeddings.

* ``build``: (re)build from the text-embedding Delta table;
* ``sync``: apply the commits since the index's Delta version (builds when missing or damaged);
* ``status``: fresh, stale, missing or damaged (exit status 0 when fresh, 1 otherwise).
"""

from __future__ import annotations

import sys


def main(argv: list[str] | None = None) -> int:
    from pipeline.cli_common import OneLineParser, fail
    from pipeline.index.sync import status, sync, text_dataset
    from pipeline.query.errors import QueryError
    from pipeline.query.library import latest_onboarding
    from pipeline.store import Store, StoreError

    p = OneLineParser(prog="python -m pipeline.index", description=__doc__.splitlines()[0])
    p.add_argument("action", choices=["build", "sync", "status"])
    p.add_argument("store", metavar="STORE")
    args = p.parse_args(argv)
    try:
        with Store.open(args.store) as store:
            ds, fp, enc = text_dataset(store, latest_onboarding(store))
            if store.delta(ds) is None:
                return fail(f"store {args.store} has no caption embeddings ({ds})")
            if args.action == "status":
                state, detail = status(store, ds, fp, enc)
                print(f"{state}: {detail}")
                return 0 if state == "fresh" else 1
            rep = sync(store, ds, fp, enc, rebuild=args.action == "build")
    except (StoreError, QueryError) as exc:
        return fail(str(exc))
    except OSError as exc:
        return fail(f"cannot write the index under {args.store}: {exc.strerror or exc}")
    man = rep.manifest
    print(
        f"{rep.action}: {rep.reason}; {rep.added} row(s) added, {rep.removed} removed in {rep.seconds:.2f}s; "
        f"index at version {man.get('delta_version')} ({man.get('n_slots')} slots, {man.get('codec')}, "
        f"nlist {man.get('nlist')}, nprobe {man.get('nprobe')}, eps {man.get('eps', 0):.4f})"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())

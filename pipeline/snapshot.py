"""One consistent snapshot of a store: every table at its version as of the latest ``runs`` commit.

A run commits its tables upstream first and its ``runs`` row last (:data:`pipeline.store.TABLE_ORDER`),
one Delta commit per table. A reader that loaded each table at its own latest version could see half of a
run that is still committing, or tables it touches late (``view_features`` on the first verified query)
from a later run than the rest. :func:`consistent_versions` instead pins every table to its newest commit
no later than the ``runs`` table's newest commit (Delta commit timestamps; one writer at a time holds the
store lock, so commits of a run precede its ``runs`` commit and commits of the next run follow it).

:func:`open_snapshot` opens a :class:`~pipeline.store.Store` pinned there and, when given a reader
:class:`~pipeline.leases.Lease`, leases the versions *before* trusting them: it writes the lease, then
computes the versions again; when compaction committed in between, it leases the newer ones. Compaction
commits every table before it reads the leases and vacuums (:mod:`pipeline.compact`), so a lease that
compaction did not see names versions that compaction has not tombstoned.

Derived data of the query path (the embedding cache of :mod:`pipeline.query.cache`, a stage-1 vector
index) must be built from the pinned store (``store.parts(dataset)``, ``store.versions()``), never from
the table folders' latest state, so a reload moves them together.
"""

from __future__ import annotations

import os

from pipeline.leases import Lease
from pipeline.store import Store


def version_at(dt, timestamp_ms: int) -> int | None:
    """The newest version of DeltaTable ``dt`` committed at or before ``timestamp_ms`` (``None``: none)."""
    limit = 4
    while True:
        hist = sorted(dt.history(limit), key=lambda h: -int(h["version"]))
        for h in hist:
            if int(h["timestamp"]) <= timestamp_ms:
                return int(h["version"])
        if len(hist) < limit:
            return None
        limit *= 4


def consistent_versions(root: str | os.PathLike) -> dict[str, int]:
    """Dataset -> version of every table of the store at ``root`` as of its newest ``runs`` commit."""
    with Store.open(root) as store:
        datasets = store.all_datasets()
        runs = store.delta("runs")
        if runs is None:  # no run finished yet: whatever is there
            return {d: store.version(d) for d in datasets}
        runs_version = runs.version()
        stamp = next(int(h["timestamp"]) for h in runs.history(1) if int(h["version"]) == runs_version)
        out = {}
        for d in datasets:
            v = runs_version if d == "runs" else version_at(store.delta(d), stamp)
            if v is not None:
                out[d] = v
        return out


def leased_versions(root: str | os.PathLike, lease: Lease, attempts: int = 5) -> dict[str, int]:
    """:func:`consistent_versions`, held by ``lease`` before they are returned (re-leased while moving)."""
    versions = consistent_versions(root)
    for _ in range(attempts):
        lease.hold(versions)
        if not lease.writable:
            break
        again = consistent_versions(root)
        if again == versions:
            break
        versions = again
    else:
        lease.hold(versions)  # still moving after ``attempts`` tries: lease the newest seen
    return versions


def open_snapshot(root: str | os.PathLike, lease: Lease | None = None) -> Store:
    """A read-only Store pinned to :func:`consistent_versions`, leased by ``lease`` first when given."""
    versions = leased_versions(root, lease) if lease is not None else consistent_versions(root)
    store = Store.open(root)
    store.pin(versions)
    return store


def pin_and_lease(store: Store, kind: str) -> Lease | None:
    """Pin an opened local read-only ``store`` to a leased consistent snapshot (the SQL shell); ``None``
    (and nothing changed) for time travel (``as_of``) and remote stores."""
    if type(store) is not Store or store.as_of is not None or store.writable:
        return None
    lease = Lease(store.root, kind)
    store.pin(leased_versions(store.root, lease))
    return lease

"""Reader leases: which table versions long-lived readers still read, so that ``compact`` spares their files.

Delta has no notion of open readers: vacuum deletes every removed file older than the retention, even when
a service still answers from the snapshot that named it. A reader (the query service, an open
``Retriever``, the analysts' SQL shell) therefore writes a *lease* into the store::

    STORE/_leases/<lease id>.json   {"id", "holder", "kind", "versions": {dataset: [v, ...]},
                                     "heartbeat": <unix seconds>, "ttl": <seconds>}

and rewrites it every ``ttl / 4`` seconds (one process-wide keeper thread renews every lease of the
process). ``compact`` reads the live leases (heartbeat + ttl not yet past) and passes each table's leased
versions to ``DeltaTable.vacuum(keep_versions=...)``; expired leases (a reader killed without closing) are
ignored and their files removed. One file per reader, not a shared table: a reader never writes what
another reader wrote (no read-modify-write, no lock, no Delta commit per heartbeat), and on object storage
each heartbeat is one PUT of a small object, atomic and read-after-write consistent (S3, GCS, Azure), and
``compact`` lists one prefix. See ``docs/architecture.md`` ("Readers and compaction").
"""

from __future__ import annotations

import atexit
import json
import logging
import os
import socket
import threading
import time
import uuid
import weakref
from dataclasses import dataclass, field
from pathlib import Path

log = logging.getLogger("pipeline.leases")

LEASE_DIR = "_leases"
#: seconds a lease stays live without a heartbeat (heartbeats come every ttl / 4)
DEFAULT_TTL = 120.0


@dataclass
class LeaseInfo:
    """One lease as read from the store."""

    id: str
    holder: str
    kind: str
    versions: dict[str, list[int]]
    heartbeat: float
    ttl: float
    path: Path | None = None

    def expired(self, now: float | None = None) -> bool:
        return (time.time() if now is None else now) > self.heartbeat + self.ttl

    def describe(self) -> str:
        return f"{self.kind} {self.id} ({self.holder})"


@dataclass(eq=False)
class Lease:
    """The lease of one reader on the store at ``root``; :meth:`hold` writes it, :meth:`release` removes it.

    Leases are best effort where the store cannot be written (a read-only mount): the reader still works,
    and compaction then protects it only through its retention period (a warning says so)."""

    root: Path
    kind: str
    ttl: float = DEFAULT_TTL
    id: str = ""
    held: list[dict[str, int]] = field(default_factory=list)
    writable: bool = True

    def __post_init__(self) -> None:
        self.root = Path(self.root)
        self.id = self.id or f"{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        self._lock = threading.Lock()
        self._io_lock = threading.Lock()
        self.renewed = 0.0  # time.monotonic() of the last write
        self.released = False
        self.pid = os.getpid()

    @property
    def path(self) -> Path:
        return self.root / LEASE_DIR / f"{self.id}.json"

    def hold(self, *snapshots: dict[str, int | None]) -> None:
        """Lease exactly ``snapshots`` (dataset -> version maps; ``None`` versions are skipped) and renew."""
        with self._lock:
            self.held = [{d: int(v) for d, v in s.items() if v is not None} for s in snapshots]
            self.released = False
        self.renew()
        KEEPER.add(self)

    def relabel(self, kind: str) -> None:
        """Say what holds the lease (``compact`` prints it): e.g. ``service`` for the query service's."""
        self.kind = kind
        if self.held:
            self.renew()

    def versions(self) -> dict[str, list[int]]:
        out: dict[str, set[int]] = {}
        for snap in self.held:
            for dataset, v in snap.items():
                out.setdefault(dataset, set()).add(v)
        return {d: sorted(vs) for d, vs in sorted(out.items())}

    def renew(self) -> None:
        """Write the lease with a fresh heartbeat (atomic: a reader of the file sees the old or the new)."""
        with self._io_lock:  # the keeper and the owner never write at once, nor after release
            self.renewed = time.monotonic()
            if self.writable and not self.released:
                self._write()

    def _write(self) -> None:
        body = {
            "id": self.id,
            "holder": f"pid {os.getpid()} on {socket.gethostname()}",
            "kind": self.kind,
            "versions": self.versions(),
            "heartbeat": time.time(),
            "ttl": self.ttl,
        }
        try:
            self.path.parent.mkdir(exist_ok=True)
            tmp = self.path.with_name(f".{self.id}.tmp")
            tmp.write_text(json.dumps(body))
            os.replace(tmp, self.path)
        except OSError as exc:
            self.writable = False
            log.warning(
                "cannot write the reader lease %s (%s): compaction protects this reader only through "
                "its retention period",
                self.path,
                exc.strerror or exc,
            )

    def release(self) -> None:
        """Remove the lease (compaction may delete this reader's files from now on)."""
        KEEPER.discard(self)
        with self._io_lock:
            self.released = True
            with self._lock:
                self.held = []
            if self.pid != os.getpid():
                return  # a forked copy: the lease is its parent's
            try:
                self.path.unlink(missing_ok=True)
            except OSError:
                pass  # read-only store: nothing was written


class _Keeper:
    """One daemon thread per process that renews every live lease every ``ttl / 4`` seconds."""

    def __init__(self) -> None:
        self._leases: weakref.WeakSet[Lease] = weakref.WeakSet()
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._wake = threading.Event()
        self._exit_hook = False

    def add(self, lease: Lease) -> None:
        with self._lock:
            self._leases.add(lease)
            if not self._exit_hook:
                atexit.register(self.release_all)  # a process that ends unclosed leaves no lease behind
                self._exit_hook = True
            if self._thread is None or not self._thread.is_alive():
                self._thread = threading.Thread(target=self._run, name="oscar-lease-keeper", daemon=True)
                self._thread.start()
        self._wake.set()  # its ttl may be shorter than the others'

    def discard(self, lease: Lease) -> None:
        with self._lock:
            self._leases.discard(lease)

    def release_all(self) -> None:
        with self._lock:
            leases = list(self._leases)
        for lease in leases:
            lease.release()  # in a forked child that exits, this leaves the parent's file alone

    def _run(self) -> None:
        while True:
            with self._lock:
                leases = list(self._leases)
                if not leases:
                    self._thread = None
                    return
            now = time.monotonic()
            for lease in leases:
                if now >= lease.renewed + lease.ttl / 4 and lease in self._leases:
                    lease.renew()
            wait = min(lease.renewed + lease.ttl / 4 for lease in leases) - time.monotonic()
            del leases  # no strong reference while waiting: a dropped Retriever's lease just expires
            self._wake.wait(max(wait, 0.02))
            self._wake.clear()


KEEPER = _Keeper()


def read_leases(root: str | os.PathLike) -> list[LeaseInfo]:
    """Every lease of the store (expired ones included); unreadable files are skipped with a warning."""
    folder = Path(root) / LEASE_DIR
    try:
        paths = sorted(p for p in folder.iterdir() if p.suffix == ".json")
    except (FileNotFoundError, NotADirectoryError):
        return []
    out = []
    for p in paths:
        try:
            d = json.loads(p.read_text())
            out.append(
                LeaseInfo(
                    str(d["id"]),
                    str(d.get("holder", "?")),
                    str(d.get("kind", "?")),
                    {str(k): [int(v) for v in vs] for k, vs in d["versions"].items()},
                    float(d["heartbeat"]),
                    float(d["ttl"]),
                    p,
                )
            )
        except FileNotFoundError:
            continue  # released while listing
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
            log.warning("ignoring unreadable lease file %s: %s", p, exc)
    return out


def live_leases(root: str | os.PathLike, now: float | None = None) -> list[LeaseInfo]:
    """The leases whose heartbeat is younger than their ttl."""
    now = time.time() if now is None else now
    return [lease for lease in read_leases(root) if not lease.expired(now)]


def remove_expired(root: str | os.PathLike, now: float | None = None) -> list[LeaseInfo]:
    """Delete the files of expired leases (``compact`` does, under the writer lock); return them."""
    gone = []
    for lease in read_leases(root):
        if lease.expired(now) and lease.path is not None:
            lease.path.unlink(missing_ok=True)
            gone.append(lease)
    return gone

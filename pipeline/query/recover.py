"""Recovering from a store that moved on: a query that meets a data file that compaction deleted reloads
the store's newest committed snapshot and runs once more; when that fails too it raises
:class:`~pipeline.query.errors.StoreUnavailable` (the service answers 503 with ``Retry-After``).

:func:`vanished_file` recognises the error (whichever layer reports it: the store's file check, pyarrow,
DuckDB, delta-rs). :func:`recovering` wraps a :class:`~pipeline.query.api.Retriever` method: calls run
under the Retriever's :class:`Gate` (shared), and a reload swaps its snapshot state in place under the
gate (exclusive), so no call ever sees half of an old and half of a new snapshot.
"""

from __future__ import annotations

import functools
import logging
import os
import re
import threading
from contextlib import contextmanager
from pathlib import Path

from pipeline.query.errors import QueryError, StoreUnavailable

log = logging.getLogger("pipeline.query")

_VANISHED = re.compile(
    r"No such file or directory|is missing \(table|\(os error 2\)|No files found that match"
    r"|Object at location .* not found|NotFound",
    re.IGNORECASE,
)
#: Retriever attributes that survive a reload in place (the models, the settings, the gate itself)
KEPT = frozenset({"models", "model", "load_seconds", "_gate", "generation", "recover", "open_args"})


def vanished_file(exc: BaseException | None, root: str | os.PathLike | None = None) -> bool:
    """Whether ``exc`` (or its cause) says that a data file is gone; with ``root``, a file of the store
    there (a missing model file or photo is not a store that moved on)."""
    roots = () if root is None else {str(root), str(Path(root).resolve())}
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, QueryError):
            return False
        text = f"{exc} {getattr(exc, 'filename', None) or ''}"
        if (isinstance(exc, FileNotFoundError) or _VANISHED.search(text)) and (
            not roots or any(r in text for r in roots)
        ):
            return True
        exc = exc.__cause__ or exc.__context__
    return False


_ANSI = re.compile(r"\x1b\[[0-9;]*m")


def one_line(exc: BaseException) -> str:
    """``exc`` as one plain line (delta-rs colours its messages)."""
    text = " ".join(_ANSI.sub("", str(exc)).split())
    return text or type(exc).__name__


def damaged(root, reason: str) -> StoreUnavailable:
    """A file of the newest snapshot is gone: not a store that moved on, so no reload can help."""
    return StoreUnavailable(
        f"the store has no newer snapshot than the one that failed ({reason}); "
        f"if this persists, run `python -m pipeline.fsck {root}`"
    )


class Gate:
    """A readers-writer lock: many calls at once, or one reload (writers go first once waiting)."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._readers = 0
        self._writing = False
        self._waiting = 0

    @contextmanager
    def reading(self):
        with self._cond:
            while self._writing or self._waiting:
                self._cond.wait()
            self._readers += 1
        try:
            yield
        finally:
            with self._cond:
                self._readers -= 1
                self._cond.notify_all()

    @contextmanager
    def writing(self):
        with self._cond:
            self._waiting += 1
            while self._writing or self._readers:
                self._cond.wait()
            self._waiting -= 1
            self._writing = True
        try:
            yield
        finally:
            with self._cond:
                self._writing = False
                self._cond.notify_all()


def newest_snapshot(root) -> dict[str, int]:
    """:func:`pipeline.snapshot.consistent_versions`, or StoreUnavailable when the log cannot be read."""
    from pipeline.snapshot import consistent_versions

    try:
        return consistent_versions(root)
    except Exception as exc:  # noqa: BLE001 - a damaged or half-copied log: nothing to reload now
        raise StoreUnavailable(
            f"the store changed and its newest snapshot cannot be read: {one_line(exc)}"
        ) from None


def reload_in_place(retriever, generation: int, reason: str) -> None:
    """Move ``retriever`` to the store's newest committed snapshot, unless another thread already did
    since ``generation``; the old snapshot is closed (its lease released). Raises StoreUnavailable."""
    with retriever._gate.writing():
        if retriever.generation != generation:
            return
        if newest_snapshot(retriever.store.root) == retriever.versions:  # damage, not compaction
            raise damaged(retriever.store.root, reason)
        try:
            fresh = retriever.reopened()
        except Exception as exc:  # noqa: BLE001 - any failure to reopen leaves the store unusable now
            raise StoreUnavailable(
                f"the store changed and its newest snapshot cannot be opened: {one_line(exc)}"
            ) from exc
        old = object.__new__(type(retriever))
        old.__dict__.update(retriever.__dict__)
        for name in [n for n in retriever.__dict__ if n not in KEPT and n not in fresh.__dict__]:
            delattr(retriever, name)  # lazily built lookups of the old snapshot
        for name, value in fresh.__dict__.items():
            if name not in KEPT:
                setattr(retriever, name, value)
        retriever.generation += 1
        old.close()
        log.warning(
            "store %s changed under a query: reloaded version %s", retriever.store.root, retriever.version
        )


def recovering(method):
    """Decorate a Retriever method: on a vanished store file, reload the newest snapshot and retry once."""

    @functools.wraps(method)
    def wrapped(self, *args, **kwargs):
        generation = self.generation
        try:
            with self._gate.reading():
                return method(self, *args, **kwargs)
        except Exception as exc:
            if not self.recover or not vanished_file(exc, self.store.root):
                raise
            first = one_line(exc)
        reload_in_place(self, generation, first)
        try:
            with self._gate.reading():
                return method(self, *args, **kwargs)
        except Exception as exc:
            if vanished_file(exc, self.store.root):
                raise StoreUnavailable(
                    f"the store changed under this query and its newest snapshot failed too: {one_line(exc)} "
                    f"(first: {first})"
                ) from None
            raise

    return wrapped

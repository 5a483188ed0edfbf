"""Which stage-1 implementation answers: the exact DuckDB scan or the index (``--stage1``).

* ``exact``: :class:`pipeline.query.stage1.TextFilter`, the reference;
* ``index``: the index of the store's caption embeddings, synced to the store state the query opened
  (built on first use); when it cannot be used (missing and the store is read-only, stale, damaged,
  another encoder) the exact path answers and every result carries a note saying why;
* ``auto``: the index from ``AUTO_MIN_ROWS`` caption rows, the exact path below (measured:
  docs/performance.md, "Stage-1 index").

Both answer through the same ``run(query, threshold, fallback_k, fallback_unit)`` contract.
"""

from __future__ import annotations

import logging

from pipeline.query.stage1 import TextFilter

STAGE1_MODES = ("exact", "index", "auto")
#: ``auto`` uses the index from this many caption rows
AUTO_MIN_ROWS = 1_000_000

log = logging.getLogger(__name__)


class IndexedTextFilter:
    """Stage 1 from an :class:`~pipeline.index.snapshot.IndexSnapshot`; view-level caption scores (an
    evaluation aid) and per-model ones (the fusion's text terms, libraries of at most
    ``fuse_all_max_models`` models) still come from the exact table, built on first use."""

    def __init__(self, snapshot, captions, threads) -> None:
        self.snapshot = snapshot
        self.dim = snapshot.dim
        self.n_rows = snapshot.n_rows
        self.notes: list[str] = []
        self.engine = "index"
        self._captions, self._threads, self._exact = captions, threads, None

    def run(self, query, threshold, fallback_k, fallback_unit="captions"):
        return self.snapshot.run(query, threshold, fallback_k, fallback_unit)

    def _exact_filter(self) -> TextFilter:
        if self._exact is None:
            self._exact = TextFilter(self._captions, self._threads)
        return self._exact

    def caption_scores(self, query):
        return self._exact_filter().caption_scores(query)

    def model_scores(self, query):
        return self._exact_filter().model_scores(query)

    def close(self) -> None:
        if self._exact is not None:
            self._exact.close()
        self.snapshot.close()


def caption_rows(store, dataset: str) -> int:
    """Rows of ``dataset`` by its Delta log (no data read)."""
    dt = store.delta(dataset)
    if dt is None:
        return 0
    add = dt.get_add_actions(flatten=True)
    return sum(x or 0 for x in add.column("num_records").to_pylist())


def open_stage1(store, tables, mode: str, threads=None):
    """The stage-1 filter for ``mode`` over the opened ``tables`` (:class:`StoreTables`); the exact one
    carries ``notes`` when the index was asked for but could not answer."""
    if mode not in STAGE1_MODES:
        raise ValueError(f"unknown stage-1 mode {mode!r}; choose from {', '.join(STAGE1_MODES)}")
    exact = None
    if mode == "exact" or (mode == "auto" and caption_rows(store, tables.text_dataset) < AUTO_MIN_ROWS):
        exact = TextFilter(tables.captions, threads)
        exact.notes, exact.engine = [], "exact"
        return exact
    note = None
    try:
        snap = open_index(store, tables)
        if snap is not None:
            return IndexedTextFilter(snap, tables.captions, threads)
        note = "stage-1 index unavailable"
    except IndexUnavailable as exc:
        note = str(exc)
    exact = TextFilter(tables.captions, threads)
    exact.engine = "exact"
    exact.notes = [f"{note}: stage 1 answered by the exact path"]
    log.warning("%s", exact.notes[0])
    return exact


class IndexUnavailable(RuntimeError):
    pass


def open_index(store, tables):
    """Sync (when the store directory is writable) and open the index for the store state of ``tables``."""
    import pyarrow as pa

    from pipeline.index.layout import index_dir, read_manifest
    from pipeline.index.snapshot import IndexDamaged, IndexSnapshot
    from pipeline.index.sync import status, sync, text_dataset

    dataset, fp, enc = text_dataset(store, tables.onboarding)
    directory = index_dir(store.root, dataset, fp)
    if store.as_of is None:
        try:
            sync(store, dataset, fp, enc)
        except Exception as exc:  # noqa: BLE001 - read-only directory, full disk, damaged files: the
            log.info("stage-1 index not synced: %s", exc)  # status check below decides, never a guess
    state, detail = status(store, dataset, fp, enc)
    if state != "fresh":
        raise IndexUnavailable(f"stage-1 index {state} ({detail})")
    active = tables.meshes.column("mesh_id").combine_chunks()
    active = pa.array(active.to_pylist(), pa.string()) if active.offset else active
    for attempt in range(2):  # a writer may replace the generation between the manifest and its files
        try:
            man = read_manifest(directory)
            if man is None or man["delta_version"] != store.version(dataset):
                raise IndexUnavailable("stage-1 index stale (another process moved it on)")
            return IndexSnapshot(directory, man, active)
        except (IndexDamaged, ValueError, KeyError) as exc:
            if attempt:
                raise IndexUnavailable(f"stage-1 index damaged ({exc})") from None
    raise AssertionError("unreachable")

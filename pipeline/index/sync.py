"""Keeping a stage-1 index in step with the Delta table: the version diff, applied incrementally.

The index records the Delta version and the data files it covers. A sync compares those with the
table's current files (the *version diff*; the change data feed is not used: the store does not enable
it, and an append's diff already names exactly the new files):

* rows are keyed by ``(mesh_id, view_index)`` at the index's fingerprint, with their ``run_id``; a row of an
  added file whose key the index holds at the same run is already indexed (``optimize`` and the
  superseded-row rewrite of ``pipeline.compact`` move rows to new files: no churn); a later run replaces
  the slot (``--force``); a new key gets a new slot;
* when files were removed, the current files' keys (no vectors) are read once, and indexed keys no
  longer present are marked dead;
* new and replaced rows go to the *delta* (scanned exactly at query time); when the delta passes
  ``FOLD_ROWS`` (or ``FOLD_FRACTION`` of the base) it is folded into the IVF base without retraining;
* drift: the mean squared distance of added rows to their IVF centroid, over the same at training. Past
  ``DRIFT_MAX`` (with at least ``DRIFT_MIN_FRACTION`` of the rows new), or once the index has grown to
  ``GROWTH_MAX`` times its trained size, the IVF is retrained; past ``DEAD_MAX`` dead slots, or when the
  encoder or fingerprint changes, it is rebuilt from the table.

Writers hold ``sync.lock`` (``fcntl``); readers never block (:mod:`pipeline.index.layout`).
"""

from __future__ import annotations

import fcntl
import os
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow.compute as pc

from pipeline.index.build import (
    build,
    key64,
    residual_of,
    stream_rows,
    vectors_of,
    write_base,
    write_delta,
)
from pipeline.index.layout import (
    LOCK,
    base_array,
    check_files,
    index_dir,
    named_files,
    read_manifest,
    remove_unnamed,
    write_manifest,
)
from pipeline.index.lookup import MeshLookup, read_ids

FOLD_ROWS = 250_000
FOLD_FRACTION = 0.05
DRIFT_MAX = 1.25
DRIFT_MIN_FRACTION = 0.01
GROWTH_MAX = 2.0
DEAD_MAX = 0.3
DRIFT_SAMPLE = 2048  # added rows the drift statistic is measured on, evenly spaced


@dataclass
class SyncReport:
    action: str  # "none" | "build" | "sync" | "fold" | "retrain" | "rebuild"
    added: int = 0
    removed: int = 0
    seconds: float = 0.0
    reason: str = ""
    manifest: dict = field(default_factory=dict, repr=False)


@contextmanager
def writer_lock(directory: Path):
    directory.mkdir(parents=True, exist_ok=True)
    fd = os.open(directory / LOCK, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        fcntl.flock(fd, fcntl.LOCK_UN)
        os.close(fd)


def text_dataset(store, onboarding) -> tuple[str, str, str]:
    """(dataset, fingerprint, encoder id) of the store's caption embeddings."""
    from pipeline.store import slug

    enc = onboarding.models["text_encoder"]
    return f"text_embeddings/{slug(enc)}", onboarding.fingerprints["embed_text"], enc


def sync(store, dataset: str, fp: str, encoder_id: str, *, rebuild: bool = False) -> SyncReport:
    """Bring the index of ``dataset`` at ``fp`` to the store's pinned version (building it if needed)."""
    t0 = time.perf_counter()
    directory = index_dir(store.root, dataset, fp)
    with writer_lock(directory):
        try:
            man = read_manifest(directory)
            problem = check_files(directory, man) if man else None
        except (ValueError, KeyError, TypeError) as exc:
            man, problem = None, f"damaged manifest ({exc})"
        if rebuild:
            why = "forced"
        elif problem:
            why = problem
        elif man is None:
            why = "no index"
        elif (man["encoder_id"], man["fingerprint"]) != (encoder_id, fp):
            why = "encoder or fingerprint changed"
        else:
            why = ""
        if why:
            man = build(store, dataset, fp, encoder_id, directory)
            return SyncReport("build", man["n_slots"], 0, time.perf_counter() - t0, why, man)
        version = store.version(dataset)
        if man["delta_version"] == version:
            return SyncReport("none", 0, 0, time.perf_counter() - t0, "up to date", man)
        if version is None or man["delta_version"] > version:
            return SyncReport("none", 0, 0, time.perf_counter() - t0, "index is ahead of this snapshot", man)
        report = _apply(store, dataset, directory, man)
        report.seconds = time.perf_counter() - t0
        return report


def _apply(store, dataset: str, directory: Path, man: dict) -> SyncReport:
    """Apply the version diff. The base's slot arrays stay memory-mapped: a commit of a few meshes reads
    the pages its keys touch, not the base's hundreds of megabytes; only a removal or a fold reads them
    whole."""
    import faiss

    fp = man["fingerprint"]
    current = {p.name: p for p in store.parts(dataset)}
    covered = set(man["files"])
    added = [current[n] for n in current if n not in covered]
    removed = covered - current.keys()
    base_run = base_array(directory, man, "run_code")
    sorted_keys, key_order = base_array(directory, man, "sorted_keys"), base_array(directory, man, "key_order")
    with np.load(directory / man["delta"]["file"], allow_pickle=False) as d:
        d_mesh, d_view, d_run = (d[k] for k in ("mesh_code", "view", "run_code"))
        d_dead = d["dead"]
    meshes = MeshLookup(
        read_ids(directory / man["base"]["meshes"]),
        base_array(directory, man, "mesh_sort"),
        man["delta"]["meshes"],
    )
    n_base = int(man["base"]["n_slots"])
    alive = np.ones(n_base + len(d_mesh), bool)
    alive[d_dead] = False
    runs = list(man["runs"])
    run_code = {r: i for i, r in enumerate(runs)}
    d_keys = key64(d_mesh, d_view)
    d_order = np.argsort(d_keys, kind="stable")
    d_sorted = d_keys[d_order]

    def slots_of(keys: np.ndarray) -> np.ndarray:
        return live_slots(keys, sorted_keys, key_order, d_sorted, d_order, alive, n_base)

    def every_slot() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(mesh code, view, run code) of every slot, base then delta: the base's arrays read whole."""
        return (
            np.concatenate([base_array(directory, man, "mesh_code"), d_mesh]),
            np.concatenate([base_array(directory, man, "view"), d_view]),
            np.concatenate([base_run, d_run]),
        )

    def runs_of(slots: np.ndarray) -> np.ndarray:
        """Run code of every slot (-1 where the slot is -1)."""
        out = np.full(len(slots), -1, np.int64)
        b, d = (slots >= 0) & (slots < n_base), slots >= n_base
        out[b] = base_run[slots[b]]
        out[d] = d_run[slots[d] - n_base]
        return out

    def later(a: str, b_code: int) -> bool:
        return a > runs[b_code]

    removed_n, resurfaced = 0, False
    new_rows: list[tuple[int, int, int, np.ndarray]] = []  # (mesh code, view, run code, vector)
    pending: dict[int, int] = {}  # key -> index in new_rows (latest run within this sync)

    def offer(codes, views, run_ids, x):
        keys = key64(codes, views)
        indexed = runs_of(slots_of(keys))  # run code of each key's live slot (-1: none)
        for i, (k, r) in enumerate(zip(keys.tolist(), run_ids, strict=True)):
            j = pending.get(k)
            if j is not None:
                if r > runs[new_rows[j][2]]:
                    rc = run_code.setdefault(r, len(runs))
                    if rc == len(runs):
                        runs.append(r)
                    new_rows[j] = (int(codes[i]), int(views[i]), rc, x[i])
                continue
            if indexed[i] >= 0 and not later(r, int(indexed[i])):
                continue  # already indexed at this run (compaction) or an older run
            rc = run_code.setdefault(r, len(runs))
            if rc == len(runs):
                runs.append(r)
            pending[k] = len(new_rows)
            new_rows.append((int(codes[i]), int(views[i]), rc, x[i]))

    for t in stream_rows(store, dataset, fp, added):
        offer(
            meshes.codes(t.column("mesh_id").combine_chunks()),
            t.column("view_index").to_numpy(),
            t.column("run_id").to_pylist(),
            vectors_of(t),
        )
    if removed:
        # which keys (at which run) the table still holds: keys only, no vectors
        cur_keys, cur_run = _current_keys(store, dataset, fp, meshes.codes, run_code)
        slot_mesh, slot_view, slot_run = every_slot()  # before this sync's new rows
        slot_keys = key64(slot_mesh, slot_view)
        live = np.flatnonzero(alive)
        pos = np.minimum(np.searchsorted(cur_keys, slot_keys[live]), max(len(cur_keys) - 1, 0))
        found = cur_keys[pos] == slot_keys[live] if len(cur_keys) else np.zeros(len(live), bool)
        alive[live[~found]] = False
        removed_n += int((~found).sum())
        stay, pos = live[found], pos[found]
        other = stay[cur_run[pos] != slot_run[stay]]  # the table's latest row of the key is another run
        if len(other) and not np.isin(slot_keys[other], np.fromiter(pending, np.int64, len(pending))).all():
            resurfaced = True  # the indexed run was removed, an older row is latest again
    # replace: old live slots of keys that get a new row die
    if pending:
        old = slots_of(np.fromiter(pending, np.int64, len(pending)))
        old = old[old >= 0]
        alive[old] = False
        removed_n += len(old)
    n_slots = n_base + len(d_mesh)
    if new_rows:
        x = np.stack([r[3] for r in new_rows]).astype(np.float32)
        with open(directory / man["vectors"], "r+b") as f:
            f.seek(n_slots * man["dim"] * 4)
            f.truncate()
            f.write(np.ascontiguousarray(x).tobytes())
            f.flush()
            os.fsync(f.fileno())
        d_mesh = np.concatenate([d_mesh, np.array([r[0] for r in new_rows], np.int32)])
        d_view = np.concatenate([d_view, np.array([r[1] for r in new_rows], np.int16)])
        d_run = np.concatenate([d_run, np.array([r[2] for r in new_rows], np.int32)])
        alive = np.concatenate([alive, np.ones(len(new_rows), bool)])
        drift = dict(man["drift"])
        drift["added_rows"] += len(new_rows)
        sample = x[np.linspace(0, len(x) - 1, min(len(x), DRIFT_SAMPLE)).astype(np.int64)]
        drift["added_residual_sum"] += residual_of(base_array(directory, man, "centroids"), sample) * len(x)
        man["drift"] = drift
    index = None  # the IVF file is read only when the base is rewritten
    n_slots = n_base + len(d_mesh)
    dead = np.flatnonzero(~alive)
    prev_names = set(named_files(man))
    man.update(
        {"delta_version": store.version(dataset), "files": sorted(current), "n_slots": n_slots, "runs": runs}
    )
    action, reason = "sync", f"{len(added)} added and {len(removed)} removed file(s)"
    dr = man["drift"]
    live_n = int(alive.sum())
    ratio = (dr["added_residual_sum"] / max(dr["added_rows"], 1)) / max(dr["train_residual"], 1e-12)
    delta_rows = n_slots - n_base
    if resurfaced:
        action, reason = "rebuild", "an indexed row was removed while an older row of its key remains"
    elif n_slots and len(dead) > DEAD_MAX * n_slots:
        action, reason = "rebuild", f"{len(dead)} of {n_slots} slots dead (> {DEAD_MAX:.0%})"
    elif dr["added_rows"] >= DRIFT_MIN_FRACTION * dr["rows_at_train"] and ratio > DRIFT_MAX:
        action, reason = "retrain", f"drift {ratio:.2f} > {DRIFT_MAX}"
    elif live_n > GROWTH_MAX * max(dr["rows_at_train"], 1):
        action, reason = "retrain", f"{live_n} rows, trained on {dr['rows_at_train']}"
    elif delta_rows > min(FOLD_ROWS, max(1000, FOLD_FRACTION * n_base)):
        action, reason = "fold", f"delta of {delta_rows} rows"
    if action == "rebuild":
        man2 = build(store, dataset, fp, man["encoder_id"], directory)
        return SyncReport("rebuild", len(new_rows), removed_n, 0.0, reason, man2)
    if action in ("retrain", "fold"):
        man["generation"] += 1
        ids = meshes.base.to_pylist() + meshes.new
        vecs = np.memmap(directory / man["vectors"], np.float32, "r", shape=(n_slots, man["dim"]))
        if index is None:
            index = faiss.read_index(str(directory / man["base"]["faiss"]))
        man.update(
            write_base(
                directory,
                man,
                vecs,
                *every_slot(),
                dead,
                ids,
                train=action == "retrain",
                index=index,
            )
        )
        man["delta"] = write_delta(directory, man["generation"], [], [], [], dead, [])
    else:
        seq = int(man["delta"].get("seq", 0)) + 1
        man["delta"] = write_delta(
            directory,
            man["generation"],
            d_mesh,
            d_view,
            d_run,
            dead,
            meshes.new,
            seq,
        )
    write_manifest(directory, man)
    remove_unnamed(directory, prev_names)
    return SyncReport(action, len(new_rows), removed_n, 0.0, reason, man)


def live_slots(
    keys: np.ndarray,
    sorted_keys: np.ndarray,
    key_order: np.ndarray,
    d_sorted: np.ndarray,
    d_order: np.ndarray,
    alive: np.ndarray,
    n_base: int,
) -> np.ndarray:
    """The live slot of every key (-1 when none): an alive base slot first, else the key's latest alive
    delta slot. ``sorted_keys``/``key_order`` are the base's keys sorted and their slots (memory-mapped: a
    binary search touches a few pages per key); ``d_sorted``/``d_order`` the same for the delta."""
    out = np.full(len(keys), -1, np.int64)
    lo, hi = np.searchsorted(sorted_keys, keys, "left"), np.searchsorted(sorted_keys, keys, "right")
    todo, j = np.flatnonzero(hi > lo), 0
    while len(todo):  # usually one base slot per key; a replaced key keeps its dead ones
        s = np.asarray(key_order[lo[todo] + j], np.int64)
        ok = alive[s]
        out[todo[ok]] = s[ok]
        j += 1
        todo = todo[~ok & (lo[todo] + j < hi[todo])]
    lo, hi = np.searchsorted(d_sorted, keys, "left"), np.searchsorted(d_sorted, keys, "right")
    todo, j = np.flatnonzero((out < 0) & (hi > lo)), 1
    while len(todo):
        s = n_base + d_order[hi[todo] - j]
        ok = alive[s]
        out[todo[ok]] = s[ok]
        j += 1
        todo = todo[~ok & (hi[todo] - j >= lo[todo])]
    return out


def _current_keys(store, dataset: str, fp: str, codes_of, run_code: dict) -> tuple[np.ndarray, np.ndarray]:
    """Every key the table holds at ``fp`` (key64, sorted) and the run code of its latest row (-1 for a
    run ``run_code`` lacks); the latest row is the highest ``run_id``, the later-written one on ties, as in
    :func:`pipeline.store.latest_rows`."""
    t = store.read(dataset, columns=["mesh_id", "view_index", "run_id"], filter=pc.field("fingerprint") == fp)
    keys = key64(codes_of(t.column("mesh_id").combine_chunks()), t.column("view_index").to_numpy())
    runs = pc.dictionary_encode(t.column("run_id").combine_chunks())
    names = runs.dictionary.to_pylist()
    rank = np.argsort(np.argsort(np.array(names, dtype=object), kind="stable"))
    idx = runs.indices.to_numpy(zero_copy_only=False)
    order = np.lexsort((rank[idx], keys))  # stable: ties by position
    k = keys[order]
    last = np.ones(len(k), bool)
    last[:-1] = k[1:] != k[:-1]
    code = np.array([run_code.get(n, -1) for n in names], np.int64)
    return k[last], code[idx[order[last]]]


def status(store, dataset: str, fp: str, encoder_id: str) -> tuple[str, str]:
    """(state, detail): state is "fresh", "stale", "missing" or "damaged" for the store's pinned version."""
    directory = index_dir(store.root, dataset, fp)
    try:
        man = read_manifest(directory)
    except ValueError as exc:
        return "damaged", str(exc)[:300]
    except OSError as exc:
        return "damaged", f"{directory / 'manifest.json'}: {str(exc)[:100]}"
    if man is None:
        return "missing", f"no stage-1 index under {directory}"
    try:
        problem = check_files(directory, man)
    except (KeyError, TypeError) as exc:
        problem = f"manifest lacks {exc}"
    if problem:
        return "damaged", problem
    if (man["encoder_id"], man["fingerprint"]) != (encoder_id, fp):
        return "stale", "built for another encoder or fingerprint"
    version = store.version(dataset)
    if man["delta_version"] != version:
        return "stale", f"covers version {man['delta_version']} of {dataset}, the table is at {version}"
    return (
        "fresh",
        f"covers version {version} of {dataset} ({man['n_slots']} slots, {man['codec']}, nlist {man['nlist']})",
    )


def index_states(store) -> list[tuple[str, str]]:
    """(state, detail) of every stage-1 index directory of the store (for fsck); the index of the latest
    onboarding's text encoder and fingerprint is checked against the table, others are listed as stale."""
    from pipeline.index.layout import INDEX_DIR
    from pipeline.query.errors import QueryError
    from pipeline.query.library import latest_onboarding

    base = store.root.joinpath(*INDEX_DIR)
    if not base.is_dir():
        return []
    try:
        current = text_dataset(store, latest_onboarding(store))
    except (QueryError, KeyError):
        current = None
    out = []
    want = index_dir(store.root, *current[:2]) if current else None
    for d in sorted(p for p in base.iterdir() if p.is_dir()):
        if d == want:
            out.append(status(store, *current))
        else:
            out.append(("stale", f"{d} is not for the store's current text encoder and fingerprint"))
    return out

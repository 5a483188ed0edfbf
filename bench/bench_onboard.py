"""Onboarding benchmark: throughput per stage, rendering views/s, peak memory, unchanged re-runs.

    python bench/bench_onboard.py [--ycb ../shared/data/ycb] [--files 100000] [--skip-full]

Prints Markdown tables (paste into docs/performance.md). Runs the real CLI in subprocesses so that
start-up, model loading and commits are all counted.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def run_cli(args: list[str]) -> tuple[float, dict, int]:
    """Wall seconds, parsed --json summary, and peak RSS (MiB) of one onboarding command."""
    t = time.perf_counter()
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    out = subprocess.run(
        [sys.executable, "-m", "pipeline.onboard", *args, "--json", "--no-progress"],
        capture_output=True,
        text=True,
        check=True,
        cwd=REPO,
    )
    wall = time.perf_counter() - t
    peak = max(before, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss) // 1024
    return wall, json.loads(out.stdout), peak


def bench_full(ycb: Path, tmp: Path, workers: int) -> None:
    store = tmp / f"store_w{workers}"
    wall, s, peak = run_cli([str(ycb), "--store", str(store), "--workers", str(workers)])
    n = s["rendered"]
    print(f"\n### Full onboarding of {n} YCB meshes, offline profile, {workers} render workers\n")
    print("| measure | value |\n|---|---|")
    print(
        f"| end to end (CLI wall, incl. start-up and model load) | {wall:.1f} s = **{n / wall:.2f} meshes/s** |"
    )
    secs = s["seconds"]
    pool = secs.get("render_pool_wall", secs.get("render", wall))
    print(
        f"| views rendered | {n * 8} in {pool:.1f} s of render-pool wall = {n * 8 / pool:.1f} views/s "
        "(sharing the 2 cores with captioning and embedding) |"
    )
    labels = {
        "render": "main thread waiting for renders",
        "render_pool_wall": "render pool wall, start-up included",
    }
    for k, v in secs.items():
        label = labels.get(k, "main-process seconds")
        print(f"| stage `{k}` ({label}) | {v:.1f} s ({v / max(n, 1) * 1000:.0f} ms/mesh) |")
    print(f"| peak RSS of the largest process | {peak} MiB |")
    print(f"| failed | {s['failed']} |")
    walls = []
    for _ in range(3):
        w, s2, _ = run_cli([str(ycb), "--store", str(store), "--workers", str(workers)])
        assert s2["rendered"] == 0 and s2["hashed"] == 0, s2
        walls.append(w)
    print(f"| unchanged re-run, CLI wall (median of 3) | **{statistics.median(walls):.2f} s** |")


def bench_render(ycb: Path, reps: int = 5) -> None:
    sys.path.insert(0, str(REPO))
    from pipeline.mesh.load import load_mesh
    from pipeline.mesh.render import Renderer
    from pipeline.mesh.settings import RenderConfig

    r = Renderer(RenderConfig())
    r.warm_up()
    rows = []
    for name in ("006_mustard_bottle", "003_cracker_box", "035_power_drill"):
        t = time.perf_counter()
        mesh = load_mesh(str(ycb / name / "textured.obj"), "obj", max_faces=10**7)
        load_s = time.perf_counter() - t
        times = []
        for _ in range(reps):
            t = time.perf_counter()
            r.render(mesh)
            times.append(time.perf_counter() - t)
        med = statistics.median(times)
        rows.append((name, load_s, med, 8 / med))
    print("\n### Rendering, one process, 512x512, 8 views per mesh (median of 5 renders)\n")
    print("| mesh | load+normalise s | 8 views s | views/s |\n|---|---|---|---|")
    for name, load_s, med, vps in rows:
        print(f"| {name} | {load_s:.2f} | {med:.3f} | {vps:.1f} |")


def bench_render_pool(ycb: Path, workers: int, n: int = 24) -> None:
    """Render-only throughput of the worker pool (load + normalise + 8 views + PNG), no models running."""
    sys.path.insert(0, str(REPO))
    from pipeline.onboard.config import OnboardConfig
    from pipeline.onboard.engines.render_pool import RenderPool

    names = sorted(p.name for p in ycb.iterdir() if (p / "textured.obj").exists())[:n]
    items = [{"mesh_id": x, "abs_path": str(ycb / x / "textured.obj"), "format": "obj"} for x in names]
    pool = RenderPool(OnboardConfig(workers=workers), "bench", workers, 120.0)
    list(pool.map(items[:workers]))  # start-up and warm-up outside the timing
    t = time.perf_counter()
    rows = [r for _, rs in pool.map(items) for r in rs]
    dt = time.perf_counter() - t
    pool.close()
    ok = sum(r.get("error") is None for r in rows)
    print(f"\n### Render pool alone, {workers} worker processes, {len(items)} YCB meshes, 512x512\n")
    print("| measure | value |\n|---|---|")
    print(f"| meshes/s (load + normalise + 8 views + PNG encode) | {len(items) / dt:.2f} |")
    print(f"| views/s | **{ok / dt:.1f}** |")


def bench_unchanged_synthetic(n: int, tmp: Path) -> None:
    """A library of ``n`` small meshes already in the store; time an unchanged re-run."""
    sys.path.insert(0, str(REPO))
    import numpy as np
    import pyarrow as pa

    from pipeline import schemas
    from pipeline.mesh.discover import identify, walk_library
    from pipeline.onboard.config import OnboardConfig
    from pipeline.store import Store, new_run_id, utcnow

    lib = tmp / "synthetic"
    t = time.perf_counter()
    for i in range(n):
        d = lib / f"d{i // 1000:03d}"
        if i % 1000 == 0:
            d.mkdir(parents=True)
        (d / f"m{i:06d}.off").write_text(
            f"OFF\n4 4 0\n0 0 0\n1 0 0\n0 1 0\n0 0 {1 + i}\n3 0 1 2\n3 0 1 3\n3 0 2 3\n3 1 2 3\n"
        )
    made = time.perf_counter() - t

    # register every file as fully onboarded (one row per table per mesh is enough for planning)
    spec = OnboardConfig().resolve()
    fps = spec.fingerprints
    root = str(lib.resolve())
    files = [identify(f, None) for f in walk_library(root)]
    run_id, now = new_run_id(), utcnow()
    ids = [f.mesh_id for f in files]
    store = Store.open(tmp / "synthetic_store", create=True)
    meshes = pa.Table.from_pylist(
        [
            {
                "mesh_id": f.mesh_id,
                "source_path": f.source_path,
                "library_root": root,
                "name": f.name,
                "format": f.format,
                "file_size": f.size,
                "mtime_ns": f.mtime_ns,
                "deps": f.deps,
                "n_vertices": 4,
                "n_faces": 4,
                "status": "active",
                "seen_at": now,
                "run_id": run_id,
            }
            for f in files
        ],
        schema=schemas.MESHES,
    )
    zeros16 = pa.array([0] * len(ids), pa.int16())
    tables = {
        "meshes": meshes,
        "views": pa.table(
            {
                "mesh_id": ids,
                "view_index": zeros16,
                "fingerprint": [fps["render"]] * len(ids),
                "run_id": [run_id] * len(ids),
            }
        ),
        "captions": pa.table(
            {
                "mesh_id": ids,
                "view_index": zeros16,
                "captioner_id": ["x"] * len(ids),
                "fingerprint": [fps["caption"]] * len(ids),
                "view_fingerprint": ["x"] * len(ids),
                "run_id": [run_id] * len(ids),
            }
        ),
    }
    vec = np.zeros((len(ids), 4), np.float32)
    vec[:, 0] = 1
    for dataset, fp in [(s.dataset, s.fingerprint) for s in spec.steps if s.stage.per_encoder]:
        tables[dataset] = pa.table(
            {
                "mesh_id": ids,
                "view_index": zeros16,
                "encoder_id": ["x"] * len(ids),
                "dim": [4] * len(ids),
                "embedding": pa.FixedSizeListArray.from_arrays(pa.array(vec.ravel()), 4),
                "fingerprint": [fp] * len(ids),
                "source_fingerprint": ["x"] * len(ids),
                "run_id": [run_id] * len(ids),
            },
            schema=schemas.embedding_schema(4),
        )
    store.commit(tables, run_id)
    store.close()
    walls = []
    for _ in range(3):
        w, s, peak = run_cli([str(lib), "--store", str(tmp / "synthetic_store")])
        assert s["rendered"] == 0 and s["hashed"] == 0 and s["skipped"] == n, s
        walls.append(w)
    print(f"\n### Unchanged re-run of a synthetic library of {n:,} mesh files\n")
    print("| measure | value |\n|---|---|")
    print(f"| library written | {made:.1f} s |")
    print(f"| unchanged re-run, CLI wall (median of 3) | **{statistics.median(walls):.2f} s** |")
    print(f"| of which planning (discover) | {s['seconds'].get('discover', 0):.2f} s |")
    print(f"| peak RSS | {peak} MiB |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--ycb", default=str(REPO.parent / "shared" / "data" / "ycb"))
    ap.add_argument("--files", type=int, default=100_000, help="synthetic library size (0 to skip)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--skip-full", action="store_true")
    args = ap.parse_args()
    ycb = Path(args.ycb)
    print(f"machine: {os.cpu_count()} CPUs, python {sys.version.split()[0]}")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        if ycb.exists():
            bench_render(ycb)
            bench_render_pool(ycb, args.workers)
            if not args.skip_full:
                bench_full(ycb, tmp, args.workers)
        else:
            print(f"(skipping YCB benchmarks: {ycb} not found)")
        if args.files:
            bench_unchanged_synthetic(args.files, tmp)


if __name__ == "__main__":
    main()

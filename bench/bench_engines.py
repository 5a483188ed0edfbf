"""Local versus Ray engine: end-to-end throughput and the per-stage costs behind the scaling model.

    python bench/bench_engines.py [--library ../shared/data/ycb] [--engines local,ray] [--json out.json]

Onboards the library into a fresh store once per engine through the real CLI (subprocesses, so Python
and Ray start-up, model loading and commits are all counted), checks that both stores hold the same
tables, and prints Markdown (paste into docs/performance.md (Engines)). Per-stage seconds are what each engine
reports: the local engine times its render pool by wall clock and the model stages in its main process;
the Ray engine sums the busy seconds of its actors (the cost of a stage, whatever the parallelism).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
STAGES = (
    "discover",
    "model_load",
    "ray_start",
    "load",
    "render",
    "caption",
    "embed_text",
    "embed_image",
    "commit",
)


def onboard(library: Path, store: Path, engine: str, extra: list[str]) -> dict:
    cmd = [sys.executable, "-m", "pipeline.onboard", str(library), "--store", str(store)]
    cmd += ["--engine", engine, "--json", "--no-progress", *extra]
    load_before = os.getloadavg()[0]
    t = time.perf_counter()
    out = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO)
    wall = time.perf_counter() - t
    if out.returncode != 0:
        raise SystemExit(f"{engine} run failed:\n{out.stderr[-3000:]}")
    summary = json.loads(out.stdout[out.stdout.index("{") :])
    size = sum(p.stat().st_size for p in store.rglob("*.parquet"))
    return {
        "engine": engine,
        "wall_s": round(wall, 2),
        "summary": summary,
        "store_bytes": size,
        "load_avg": [round(load_before, 2), round(os.getloadavg()[0], 2)],
    }


def same_tables(a: Path, b: Path) -> str:
    """'yes', or what differs (embeddings compared to 1e-6)."""
    sys.path.insert(0, str(REPO))
    import numpy as np

    from pipeline.store import Store

    def rows(path):
        s, out = Store.open(path), {}
        for table in ("meshes", "views", "captions", "errors", "text_embeddings", "image_embeddings"):
            for d in s.datasets(table):
                t = s.read_latest(d) if table != "errors" else s.read(d)
                t = t.drop_columns([c for c in t.column_names if c in {"run_id", "seen_at", "at"}])
                out[d] = sorted(
                    t.to_pylist(), key=lambda r: repr({k: v for k, v in r.items() if k != "embedding"})
                )
        return out

    ra, rb = rows(a), rows(b)
    if sorted(ra) != sorted(rb):
        return f"different datasets: {sorted(set(ra) ^ set(rb))}"
    for d in ra:
        if len(ra[d]) != len(rb[d]):
            return f"{d}: {len(ra[d])} vs {len(rb[d])} rows"
        for x, y in zip(ra[d], rb[d], strict=True):
            ex, ey = x.pop("embedding", None), y.pop("embedding", None)
            if x != y or (ex is not None and not np.allclose(ex, ey, atol=1e-6)):
                return f"{d}: rows differ"
    return "yes"


def report(results: list[dict], n_cpus: int, equal: str | None) -> None:
    print(
        f"\n### Local vs Ray engine, {results[0]['summary']['rendered']} meshes, {n_cpus} CPUs, offline profile\n"
    )
    print(
        "| engine | wall s (CLI) | meshes/s | "
        + " | ".join(f"{s} s" for s in STAGES)
        + " | store MiB | load avg |"
    )
    print("|---|---|---|" + "---|" * len(STAGES) + "---|---|")
    for r in results:
        s = r["summary"]
        n = max(s["rendered"], 1)
        cells = [f"{s['seconds'].get(k, 0):.1f}" if k in s["seconds"] else "-" for k in STAGES]
        print(
            f"| {r['engine']} | {r['wall_s']:.1f} | **{n / r['wall_s']:.3f}** | "
            + " | ".join(cells)
            + f" | {r['store_bytes'] / 2**20:.1f} | {r['load_avg'][0]:g} -> {r['load_avg'][1]:g} |"
        )
    print("\nPer-mesh stage costs (seconds per mesh; Ray: summed actor busy time, local: see the note):\n")
    print("| engine | " + " | ".join(STAGES) + " |")
    print("|---|" + "---|" * len(STAGES))
    for r in results:
        s = r["summary"]
        n = max(s["rendered"], 1)
        print(
            f"| {r['engine']} | "
            + " | ".join(f"{s['seconds'][k] / n:.3f}" if k in s["seconds"] else "-" for k in STAGES)
            + " |"
        )
    if equal is not None:
        print(f"\nSame tables from both engines (embeddings to 1e-6): **{equal}**")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--library", default=str(REPO.parent / "shared" / "data" / "ycb"))
    p.add_argument("--engines", default="local,ray")
    p.add_argument("--workers", type=int, default=2, help="local render processes")
    p.add_argument("--keep", metavar="DIR", help="build the stores here and keep them")
    p.add_argument("--json", metavar="FILE", help="also write the raw results as JSON")
    args = p.parse_args()
    library = Path(args.library)
    if not library.is_dir():
        raise SystemExit(f"no library at {library}")
    tmp = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="bench_engines_"))
    results, stores = [], []
    for engine in args.engines.split(","):
        store = tmp / f"store_{engine}"
        if store.exists():
            raise SystemExit(f"{store} exists; remove it or pick another --keep")
        extra = ["--workers", str(args.workers)] if engine == "local" else []
        results.append(onboard(library, store, engine, extra))
        stores.append(store)
        print(f"{engine}: {results[-1]['wall_s']} s", file=sys.stderr)
    equal = same_tables(stores[0], stores[1]) if len(stores) == 2 else None
    n_cpus = os.cpu_count() or 1
    report(results, n_cpus, equal)
    if args.json:
        meta = {"cpus": n_cpus, "machine": platform.platform(), "python": platform.python_version()}
        Path(args.json).write_text(
            json.dumps({"meta": meta, "results": results, "same_tables": equal}, indent=2)
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())

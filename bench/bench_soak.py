"""Soak of the query service while the store changes under it (issue 22), on the loopback (127.0.0.1 only).

    python bench/bench_soak.py --clients 4 --quiet 20

Steps, each bounded:

1. Onboards a small library (``--meshes`` YCB folders copied from ``--ycb``) into a fresh store under a
   temporary folder, and starts ``python -m pipeline.serve`` on it.
2. ``--clients`` threads POST /query (the sample photo, box, prompt) for the whole run; each answer is
   checked (200 and well-formed JSON, or a transport error / 5xx counted as a failure).
3. Timeline: ``--quiet`` seconds untouched; onboarding of ``--add`` more meshes; ``python -m pipeline.compact
   STORE --retention-hours 0``; one mesh removed from the library and onboarding again; compaction again;
   ``--quiet`` seconds more. After each compaction, every data file of the versions the service's live
   leases hold must still exist; at the end every added mesh must be served (GET /meshes/<id>: 200) and the
   removed one not (404).

Targets (issue 22): 0 answers of 5xx; p99 of the queries started during a compaction within 3x the quiet
p99; compaction with retention 0 removes no file the live service reads. Results: docs/serve.md.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from bench_serve import BOX, PHOTO, PROMPT, free_port, pct, start_server  # noqa: E402

YCB = Path(os.environ.get("OSCAR_SHARED_DATA", REPO.parent / "shared" / "data")) / "ycb"
MESHES = "006_mustard_bottle,005_tomato_soup_can,011_banana,061_foam_brick"
ADD = "003_cracker_box,025_mug"


class Recorder:
    """Client threads posting queries until stopped; every request as (start, ms, status, ok)."""

    def __init__(self, url: str, clients: int, data: bytes) -> None:
        self.url, self.clients, self.data = url, clients, data
        self.rows: list[tuple[float, float, int, bool]] = []
        self.failures: Counter = Counter()
        self.lock = threading.Lock()
        self.stop = threading.Event()
        self.threads = [threading.Thread(target=self._client, daemon=True) for _ in range(clients)]

    def _client(self) -> None:
        import httpx

        form = {"prompt": PROMPT, "box": BOX}
        with httpx.Client(base_url=self.url, timeout=120) as http:
            while not self.stop.is_set():
                t0 = time.monotonic()
                try:
                    r = http.post("/query", files={"image": ("tabletop.jpg", self.data)}, data=form)
                    status, why = r.status_code, None
                    if status == 200:
                        body = r.json()
                        if not body.get("candidates") or not all("mesh_id" in c for c in body["candidates"]):
                            why = "200 but malformed"
                    else:
                        why = f"{status} {r.text[:160]}"
                except (httpx.HTTPError, ValueError) as exc:
                    status, why = 0, f"{type(exc).__name__}: {exc}"
                ms = (time.monotonic() - t0) * 1000
                with self.lock:
                    self.rows.append((t0, ms, status, why is None))
                    if why is not None:
                        self.failures[why[:160]] += 1

    def start(self) -> None:
        for t in self.threads:
            t.start()

    def finish(self) -> None:
        self.stop.set()
        for t in self.threads:
            t.join()

    def window(self, t0: float, t1: float) -> list[float]:
        with self.lock:
            return [ms for start, ms, _, ok in self.rows if t0 <= start < t1 and ok]


def run(cmd: list[str], env: dict) -> tuple[float, float, str]:
    """(start, end, stdout) of a command that must succeed."""
    t0 = time.monotonic()
    p = subprocess.run(cmd, env=env, cwd=REPO, capture_output=True, text=True)
    t1 = time.monotonic()
    if p.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({p.returncode}): {p.stderr.strip()[-400:]}")
    return t0, t1, p.stdout


def leased_files_missing(store: Path) -> tuple[int, int]:
    """(files the service's live leases need, how many of them are missing)."""
    from deltalake import DeltaTable

    from pipeline.leases import live_leases

    need = set()
    for lease in live_leases(store):
        if lease.kind != "service":
            continue
        for dataset, versions in lease.versions.items():
            for v in versions:
                for uri in DeltaTable(str(store / dataset), version=v).file_uris():
                    need.add(Path(uri.removeprefix("file://")))
    return len(need), sum(1 for p in need if not p.exists())


def mesh_ids(store: Path, names: list[str]) -> dict[str, str]:
    from pipeline.store import Store

    with Store.open(store) as s:
        rows = s.read_latest("meshes", columns=["mesh_id", "name"]).to_pylist()
    return {r["name"]: r["mesh_id"] for r in rows if r["name"] in names}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--ycb", type=Path, default=YCB)
    p.add_argument("--meshes", default=MESHES, help="comma-separated YCB folders of the first store")
    p.add_argument("--add", default=ADD, help="comma-separated YCB folders onboarded while serving")
    p.add_argument("--remove", default="011_banana", help="the mesh folder removed from the library")
    p.add_argument("--clients", type=int, default=4)
    p.add_argument("--quiet", type=float, default=20.0, help="seconds of load before and after the changes")
    p.add_argument("--work", type=Path, default=None, help="folder for the library and store (default: tmp)")
    args = p.parse_args(argv)
    import httpx

    work = Path(args.work or tempfile.mkdtemp(prefix="oscar-soak-"))
    lib, store = work / "lib", work / "store"
    shutil.rmtree(work, ignore_errors=True)
    lib.mkdir(parents=True)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    for name in args.meshes.split(","):
        shutil.copytree(args.ycb / name, lib / name)
    onboard = [sys.executable, "-m", "pipeline.onboard", str(lib), "--store", str(store)]
    compact = [sys.executable, "-m", "pipeline.compact", str(store), "--retention-hours", "0"]
    t0, t1, _ = run(onboard, env)
    print(f"first store: {len(args.meshes.split(','))} meshes onboarded in {t1 - t0:.0f} s")
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    server = start_server(store, port, ["--workers", "2"])
    rec = Recorder(url, args.clients, PHOTO.read_bytes())
    phases: list[tuple[str, float, float]] = []
    compactions = []
    try:
        rec.start()
        q0 = time.monotonic()
        time.sleep(args.quiet)
        phases.append(("quiet", q0, time.monotonic()))
        added = args.add.split(",")
        for name in added:
            shutil.copytree(args.ycb / name, lib / name)
        phases.append((f"onboard +{len(added)}", *run(onboard, env)[:2]))
        c0, c1, out = run(compact, env)
        phases.append(("compact (retention 0)", c0, c1))
        compactions.append((out, leased_files_missing(store)))
        shutil.rmtree(lib / args.remove)
        phases.append(("onboard, 1 removed", *run(onboard, env)[:2]))
        c0, c1, out = run(compact, env)
        phases.append(("compact (retention 0)", c0, c1))
        compactions.append((out, leased_files_missing(store)))
        t0 = time.monotonic()
        time.sleep(args.quiet)
        phases.append(("quiet after", t0, time.monotonic()))
        ids = mesh_ids(store, [*added, args.remove])
        served = {n: httpx.get(f"{url}/meshes/{ids[n]}", timeout=30).status_code for n in ids}
    finally:
        rec.finish()
        server.terminate()
        server.wait(timeout=60)
    codes = Counter(status for _, _, status, _ in rec.rows)
    quiet = rec.window(phases[0][1], phases[0][2])
    print(f"\n{len(rec.rows)} requests, {args.clients} clients; status counts {dict(codes)}")
    print("| phase | seconds | answers | p50 ms | p99 ms | p99 / quiet p99 |")
    print("|---|---|---|---|---|---|")
    for name, a, b in phases:
        w = rec.window(a, b)
        ratio = pct(w, 99) / pct(quiet, 99) if w else float("nan")
        print(f"| {name} | {b - a:.1f} | {len(w)} | {pct(w, 50):.0f} | {pct(w, 99):.0f} | {ratio:.2f} |")
    for i, (out, (need, missing)) in enumerate(compactions, 1):
        kept = [line for line in out.splitlines() if "kept for live readers" in line]
        print(
            f"compaction {i}: {len(kept)} tables kept files for live readers; the service's leases need "
            f"{need} files, {missing} missing"
        )
    print(f"served after the run (GET /meshes/<id>): {served}")
    if rec.failures:
        print("failures:", dict(rec.failures.most_common(5)))
    five = sum(n for c, n in codes.items() if c >= 500)
    ok = (
        five == 0
        and not rec.failures
        and all(m == 0 for _, (_, m) in compactions)
        and all(served[n] == 200 for n in added)
        and served[args.remove] == 404
    )
    print(f"5xx answers: {five}; targets met: {ok}")
    if args.work is None:
        shutil.rmtree(work, ignore_errors=True)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

"""Cold start of the query CLI against a bare ``import torch``, measured in the same run.

    python bench/bench_coldstart.py --store data/store --runs 5

Each round runs, as fresh processes and in turn: ``python -c "import torch"``, ``python -m pipeline.query
--help`` and one full offline query (``data/queries/tabletop.jpg``, box 318,200,408,450); the table gives
each command's median wall time and its ratio to the torch import. Targets (issue 11): a query at most 1.5x
the torch import, ``--help`` under 0.3 s. Results: docs/performance.md (Cold start).
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def commands(store: str, python: str) -> dict[str, list[str]]:
    query = [
        python,
        "-m",
        "pipeline.query",
        "--store",
        store,
        "--image",
        str(REPO / "data/queries/tabletop.jpg"),
        "--box",
        "318,200,408,450",
        "--prompt",
        "the yellow mustard bottle",
        "--top",
        "3",
    ]
    return {
        'python -c "import torch"': [python, "-c", "import torch"],
        "python -m pipeline.query --help": [python, "-m", "pipeline.query", "--help"],
        "python -m pipeline.query (one query)": query,
    }


def run_once(argv: list[str], env: dict) -> float:
    t0 = time.perf_counter()
    out = subprocess.run(argv, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    wall = time.perf_counter() - t0
    if out.returncode != 0:
        raise SystemExit(f"{' '.join(argv)} failed ({out.returncode}): {out.stderr.strip()[-500:]}")
    return wall


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--store", required=True, help="an onboarded offline store (e.g. the sample store)")
    p.add_argument("--runs", type=int, default=5, help="rounds (median reported; default 5)")
    p.add_argument("--python", default=sys.executable)
    args = p.parse_args(argv)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    cmds = commands(args.store, args.python)
    times: dict[str, list[float]] = {name: [] for name in cmds}
    for cmd in cmds.values():  # warm the page cache once, untimed
        run_once(cmd, env)
    for _ in range(max(1, args.runs)):
        for name, cmd in cmds.items():  # interleaved, so machine load hits every command alike
            times[name].append(run_once(cmd, env))
    base = statistics.median(times['python -c "import torch"'])
    print(f"{'command':40s} {'median s':>9s} {'min s':>7s} {'x torch':>8s}   (runs: {args.runs})")
    for name, ts in times.items():
        med = statistics.median(ts)
        print(f"{name:40s} {med:9.3f} {min(ts):7.3f} {med / base:8.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

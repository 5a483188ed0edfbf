"""Cold start of the query CLI against a bare ``import torch``, measured in the same run.

    python bench/bench_coldstart.py --store data/store --runs 5

Each round runs, as fresh processes and in turn: ``python -c "import torch"``, ``python -m pipeline.query
--help`` and one full offline query (``data/queries/tabletop.jpg``, box 318,200,408,450); the table gives
each command's median wall time and its ratio to the torch import. Targets (issue 11): a query at most 1.5x
the torch import, ``--help`` under 0.3 s. ``--baseline DIR`` adds the same two pipeline commands run from
another checkout (e.g. a worktree of main), interleaved in every round: a before/after comparison on one
machine state. Results: docs/performance.md (Cold start).
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


def commands(store: str, python: str, repo: Path = REPO) -> dict[str, list[str]]:
    query = [
        python,
        "-m",
        "pipeline.query",
        "--store",
        store,
        "--image",
        str(repo / "data/queries/tabletop.jpg"),
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
    """Wall seconds of ``argv`` run in the checkout that ``env`` puts on the path."""
    t0 = time.perf_counter()
    cwd = env["PYTHONPATH"]  # the checkout root (this one, or --baseline)
    out = subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
    wall = time.perf_counter() - t0
    if out.returncode != 0:
        raise SystemExit(f"{' '.join(argv)} failed ({out.returncode}): {out.stderr.strip()[-500:]}")
    return wall


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--store", required=True, help="an onboarded offline store (e.g. the sample store)")
    p.add_argument("--runs", type=int, default=5, help="rounds (median reported; default 5)")
    p.add_argument("--python", default=sys.executable)
    p.add_argument(
        "--baseline", type=Path, help="another checkout whose --help and query run interleaved too"
    )
    args = p.parse_args(argv)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    cmds = {name: (cmd, env) for name, cmd in commands(args.store, args.python).items()}
    if args.baseline:
        base_env = {**os.environ, "PYTHONPATH": str(args.baseline.resolve())}
        for name, cmd in list(commands(args.store, args.python, args.baseline.resolve()).items())[1:]:
            cmds[f"{name} [baseline]"] = (cmd, base_env)
    times: dict[str, list[float]] = {name: [] for name in cmds}
    for cmd, cmd_env in cmds.values():  # warm the page cache once, untimed
        run_once(cmd, cmd_env)
    for _ in range(max(1, args.runs)):
        for name, (cmd, cmd_env) in cmds.items():  # interleaved, so machine load hits every command alike
            times[name].append(run_once(cmd, cmd_env))
    base = statistics.median(times['python -c "import torch"'])
    print(f"{'command':51s} {'median s':>9s} {'min s':>7s} {'x torch':>8s}   (runs: {args.runs})")
    for name, ts in times.items():
        med = statistics.median(ts)
        print(f"{name:51s} {med:9.3f} {min(ts):7.3f} {med / base:8.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

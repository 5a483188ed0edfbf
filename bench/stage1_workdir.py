"""What ``bench/bench_stage1_index.py`` leaves in its ``--workdir`` (the synthetic store with its stage-1
index, the queries and their taus), opened for the analysis benchmarks that reuse it."""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass
class Workdir:
    directory: Path  # the index directory
    manifest: dict
    index: object  # the faiss index of the base
    queries: np.ndarray
    taus: np.ndarray
    tau_queries: list[int]  # the first ``--queries`` queries that have a tau


def add_arguments(p: argparse.ArgumentParser, queries: int) -> None:
    """The options naming a bench_stage1_index work folder and how many of its tau queries to use."""
    p.add_argument("--workdir", type=Path, required=True, help="bench_stage1_index.py's --workdir")
    p.add_argument("--rows", type=int, required=True)
    p.add_argument("--dim", type=int, default=384)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--queries", type=int, default=queries, help="tau queries used (the first ones)")
    p.add_argument("--threads", type=int, default=2)


def open_workdir(a: argparse.Namespace) -> Workdir:
    """The work folder of ``a`` (exits with a one-line error when it holds no index)."""
    import faiss

    faiss.omp_set_num_threads(a.threads)
    root = a.workdir / f"store-{a.rows}-{a.dim}-{a.seed}" / "_index" / "stage1"
    found = sorted(root.glob("*/manifest.json"))
    if not found:
        sys.exit(f"error: no stage-1 index under {root} (run bench/bench_stage1_index.py first)")
    man = json.loads(found[0].read_text())
    index = faiss.read_index(str(found[0].parent / man["base"]["faiss"]))
    z = np.load(a.workdir / f"queries-{a.rows}.npz")
    q, taus = z["queries"], z["taus"]
    sel = [i for i in range(len(q)) if np.isfinite(taus[i])][: a.queries]
    return Workdir(found[0].parent, man, index, q, taus, sel)

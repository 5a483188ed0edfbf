"""Does a long-lived Retriever keep Python objects per query? RSS and tracemalloc over N queries.

    python bench/bench_memory.py --store STORE [--queries 2000]

Runs the sample query (tabletop photo, box, "the yellow mustard bottle") on 2 threads, as the service's
2 workers do, and prints the process RSS and the Python-level allocations (tracemalloc) every quarter, then
after ``gc.collect()``, with the five largest allocation sites still alive. Growth in tracemalloc's number
after the collection would be a leak in Python code; RSS alone also moves with the C allocator's arenas.
Results: docs/performance.md ("Query service").
"""

from __future__ import annotations

import argparse
import gc
import os
import sys
import tracemalloc
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from bench_serve import rss_mb  # a sibling script: this folder is on sys.path when run as a file

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--store", required=True)
    p.add_argument("--queries", type=int, default=2000)
    args = p.parse_args()
    from pipeline.threads import apply_torch_threads

    apply_torch_threads(1)
    from pipeline.query import Retriever

    photo = str(REPO / "data" / "queries" / "tabletop.jpg")
    with Retriever.open(args.store, profile="offline") as r, ThreadPoolExecutor(2) as ex:

        def one(_):
            return r.query(photo, "the yellow mustard bottle", box=(318, 200, 408, 450))

        list(ex.map(one, range(50)))  # warm-up
        tracemalloc.start()
        base = tracemalloc.take_snapshot()
        print(f"    0 queries: RSS {rss_mb(os.getpid()):.1f} MiB, Python allocations 0.00 MiB", flush=True)
        for i in range(1, 5):
            list(ex.map(one, range(args.queries // 4)))
            traced = tracemalloc.get_traced_memory()[0] / 2**20
            print(
                f"{i * args.queries // 4:5d} queries: RSS {rss_mb(os.getpid()):.1f} MiB, Python allocations {traced:.2f} MiB"
            )
        gc.collect()
        traced = tracemalloc.get_traced_memory()[0] / 2**20
        print(f"after gc.collect(): RSS {rss_mb(os.getpid()):.1f} MiB, Python allocations {traced:.2f} MiB")
        for stat in tracemalloc.take_snapshot().compare_to(base, "lineno")[:5]:
            print("   ", stat)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

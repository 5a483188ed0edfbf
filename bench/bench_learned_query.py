"""Warm masked query latency with and without the learned view encoder, interleaved in one process.

    python bench/bench_learned_query.py --store STORE --queries Q.jsonl [--n 6] [--repeats 2] [--torch-threads N]

Opens two Retrievers on the same store (the default, and ``--model learned_encoder=none``), warms both,
then alternates its configurations over the first ``--n`` queries (masks, verification on by default):
the default, the default with the learned ROI embedding run in turn instead of beside the rest
(``OSCAR_OVERLAP_EMBED=0``, pipeline/query/overlap.py), descriptor only, the default with every patch
feature computed, the runner-up's patch agreement included (what a calibration reading ``patch_lead``
costs), and, on a store with a query
adapter (pipeline/adapter), the default without it (``--no-adapter``). Prints the p50 of the total
and of the embedding step for each, and of the verdict's patch agreement (pipeline/query/patches.py; its
view cache is cleared before every query, as in a library too large for the top-1 to repeat), and the
ratios (the numbers that survive a loaded machine).
``--torch-threads N`` sets torch's and BLAS's threads as the query CLI and the service do (their default is
half the cores, 1 on 2 cores); without it, the libraries' own defaults (every core).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--store", required=True)
    p.add_argument("--queries", required=True)
    p.add_argument("--n", type=int, default=6)
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--torch-threads", type=int, default=None, help="as the query CLI's (default: every core)")
    args = p.parse_args()
    if args.torch_threads:
        from pipeline.threads import apply_torch_threads

        apply_torch_threads(args.torch_threads)  # before NumPy and torch are imported
    from pipeline.evaluate.datasets import load_queries
    from pipeline.query import Retriever

    qs = [q for q in load_queries(args.queries) if q.mask is not None][: args.n]
    from pipeline.query.overlap import OVERLAP_ENV

    learned = Retriever.open(args.store)
    rs = {
        "learned": (learned, "1"),
        "learned, in turn": (learned, "0"),
        "descriptor": (Retriever.open(args.store, model_overrides={"learned_encoder": "none"}), "1"),
    }
    lead = Retriever.open(args.store)  # every patch feature, the runner-up's lead (LEAD_FEATURES) included
    if lead.ranking.patches is not None:
        lead.ranking.patches.always = True
        rs["learned, runner-up patches"] = (lead, "1")
    if learned.tables.adapter is not None:
        rs["learned, no adapter"] = (Retriever.open(args.store, settings_changes={"adapter": False}), "1")
    for r, _ in rs.values():
        r.query(qs[0].image, qs[0].prompt, mask=qs[0].mask)  # warm
    total = {k: [] for k in rs}
    embed = {k: [] for k in rs}
    patches = {k: [] for k in rs}
    for _ in range(args.repeats):
        for q in qs:
            for k, (r, overlap) in rs.items():
                os.environ[OVERLAP_ENV] = overlap
                if r.ranking.patches is not None:  # the top-1's view tokens as in a large library: uncached
                    r.ranking.patches.clear()
                t0 = time.perf_counter()
                res = r.query(q.image, q.prompt, mask=q.mask)
                total[k].append(1000 * (time.perf_counter() - t0))
                embed[k].append(res.timings["embed_ms"])
                if "patches_ms" in res.timings:
                    patches[k].append(res.timings["patches_ms"])
    for k in rs:
        print(
            f"{k}: p50 total {statistics.median(total[k]):.1f} ms, "
            f"p50 embed {statistics.median(embed[k]):.1f} ms, "
            + (f"p50 patch agreement {statistics.median(patches[k]):.1f} ms, " if patches[k] else "")
            + f"n {len(total[k])}"
        )
    p50 = {k: statistics.median(v) for k, v in total.items()}
    print(f"ratio learned / descriptor p50: {p50['learned'] / p50['descriptor']:.2f}")
    print(f"ratio learned / learned in turn p50: {p50['learned'] / p50['learned, in turn']:.2f}")
    if "learned, runner-up patches" in p50:
        print(f"ratio learned with the runner-up's patches / learned p50: {p50['learned, runner-up patches'] / p50['learned']:.2f}")
    if "learned, no adapter" in p50:
        print(f"ratio learned / learned without the adapter p50: {p50['learned'] / p50['learned, no adapter']:.2f}")
    for r in {id(r): r for r, _ in rs.values()}.values():
        r.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

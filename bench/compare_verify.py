"""Top-1 / top-5 of the offline query path with and without local-feature verification, on one query set.

    python bench/compare_verify.py --store STORE --queries QUERIES.jsonl [--boxes-only] [--every N] \
        [--taus 0.4,0.5]

Each query's ROI and embedding (with its ROI keypoints) are computed once; then it is ranked in two-stage
and image-only mode, unverified and verified (the default ``VerifyConfig``), so the four settings see the
same ROIs; ``--taus`` adds two-stage + verify at other stage-1 thresholds. ``--every N`` keeps every N-th
query (e.g. one per mesh of a 5-per-mesh synthetic set). Instance level: a query is a hit when one of its
expected models is at rank 1 (top-5: within the first 5).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--store", required=True)
    p.add_argument("--queries", required=True)
    p.add_argument("--boxes-only", action="store_true", help="drop the masks: box ROIs (GrabCut)")
    p.add_argument("--every", type=int, default=1, help="keep every N-th query (default: all)")
    p.add_argument("--roi-keypoints", type=int, help="VerifyConfig.roi_keypoints (default: 384)")
    p.add_argument("--view-keypoints", type=int, help="VerifyConfig.view_keypoints (default: 192)")
    p.add_argument(
        "--taus", help="also rank two-stage + verify at these stage-1 thresholds (comma list), e.g. 0.4,0.5"
    )
    p.add_argument(
        "--box-segmenter", help="box -> mask without masks: grabcut (default), saliency-grabcut, ..."
    )
    p.add_argument("--json", help="write per-query ranks and the summary here")
    args = p.parse_args()

    import numpy as np

    from pipeline.evaluate.datasets import drop_mask, load_queries
    from pipeline.evaluate.library import Library, read_store_meshes

    queries = load_queries(args.queries)[:: max(1, args.every)]
    if args.boxes_only:
        queries = [drop_mask(q) for q in queries]
    library = Library(read_store_meshes(args.store), None, {})
    from pipeline.query import Retriever

    settings = {
        "two-stage": ("two-stage", False),
        "two-stage+verify": ("two-stage", True),
        "image-only": ("image-only", False),
        "image-only+verify": ("image-only", True),
    }
    taus = [float(t) for t in args.taus.split(",")] if args.taus else []
    settings.update({f"two-stage+verify@tau{t:g}": ("two-stage", True, t) for t in taus})
    ranks: dict[str, list[int]] = {k: [] for k in settings}
    rows, t_verify = [], []
    changes = {"verify": True, "box_segmenter": args.box_segmenter}
    with Retriever.open(args.store, profile="offline", settings_changes=changes) as r:
        import dataclasses

        knobs = {"roi_keypoints": args.roi_keypoints, "view_keypoints": args.view_keypoints}
        r.verifier.cfg = dataclasses.replace(r.verifier.cfg, **{k: v for k, v in knobs.items() if v})
        for q in queries:
            expected = set().union(*(library.resolve(e) for e in q.expected))
            roi = r.make_roi(q.image, q.prompt, box=q.box, mask=q.mask)
            emb = r.embed(roi, q.prompt)
            row = {"query_id": q.query_id}
            for key, (mode, verify, *tau) in settings.items():
                t0 = time.perf_counter()
                res = r.rank(emb, mode, top=r.n_meshes, verify=verify, threshold=tau[0] if tau else None)
                if key == "two-stage+verify":
                    t_verify.append(time.perf_counter() - t0)
                hit = [c.rank for c in res.candidates if c.mesh_id in expected]
                rank = min(hit) if hit else 10**6
                ranks[key].append(rank)
                row[key] = rank
            rows.append(row)
            print(json.dumps(row), flush=True)
    summary = {
        k: {
            "top1": round(float(np.mean(np.array(v) <= 1)), 3),
            "top5": round(float(np.mean(np.array(v) <= 5)), 3),
        }
        for k, v in ranks.items()
    }
    summary["n"] = len(queries)
    summary["median_rank_verify_ms"] = round(1000 * float(np.median(t_verify)), 1) if t_verify else None
    print(json.dumps(summary, indent=2))
    if args.json:
        Path(args.json).write_text(json.dumps({"summary": summary, "queries": rows}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

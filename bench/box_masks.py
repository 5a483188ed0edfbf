"""Box to mask on labelled photos: IoU of each offline box segmenter's mask with the labelled mask.

    python bench/box_masks.py --queries data/queries/ycb_photos.jsonl [--segmenters grabcut,saliency,...]

For every query with both a box and a mask, each segmenter (``pipeline.query.roi.BOX_SEGMENTERS``) splits
the object from the box; a segmenter that gives up (``None``: nothing, or a sliver) scores the box itself,
as the query path does. Prints the IoU per query and the median / mean IoU, the share of queries with IoU
>= 0.5 and the milliseconds per box of each segmenter.
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
    p.add_argument("--queries", required=True)
    p.add_argument("--segmenters", default="grabcut,saliency-grabcut,saliency")
    p.add_argument("--json")
    args = p.parse_args()
    import numpy as np

    from pipeline.evaluate.datasets import load_queries
    from pipeline.query.images import box_to_working, load_mask, load_photo
    from pipeline.query.roi import BOX_SEGMENTERS, box_mask

    names = args.segmenters.split(",")
    rows, ms = [], {n: [] for n in names}
    for q in load_queries(args.queries):
        if q.box is None or q.mask is None:
            continue
        photo = load_photo(q.image)
        truth = load_mask(q.mask, photo, 4)
        box = box_to_working(q.box, photo, 4)
        row = {"query_id": q.query_id}
        for n in names:
            t0 = time.perf_counter()
            m = BOX_SEGMENTERS[n](photo.image, box)
            ms[n].append(1000 * (time.perf_counter() - t0))
            fell_back = m is None
            if m is None:
                m = box_mask(truth.shape, box)
            iou = float((m & truth).sum() / max((m | truth).sum(), 1))
            row[n] = round(iou, 3)
            row[f"{n}_box"] = fell_back
        rows.append(row)
        print(json.dumps(row), flush=True)
    summary = {
        n: {
            "median_iou": round(float(np.median([r[n] for r in rows])), 3),
            "mean_iou": round(float(np.mean([r[n] for r in rows])), 3),
            "iou>=0.5": round(float(np.mean([r[n] >= 0.5 for r in rows])), 3),
            "fell_back_to_box": int(sum(r[f"{n}_box"] for r in rows)),
            "median_ms": round(float(np.median(ms[n][1:] or ms[n])), 1),
        }
        for n in names
    }
    summary["n"] = len(rows)
    print(json.dumps(summary, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps({"summary": summary, "queries": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

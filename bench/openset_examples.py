"""The open-set answers of one query set, for replaying calibrations on them (no fit, no choice).

    python bench/openset_examples.py --store STORE --queries QUERIES.jsonl --out EXAMPLES.jsonl \
        [--rois mask[,box]]

Answers each query's ROI kinds with the store's default ranking variants against the full store and, for
the 21 YCB-Video objects, against the store without them (:func:`pipeline.evaluate.openset.collect`, as
``python -m pipeline.evaluate openset`` does before it fits), and writes the examples (features, right or
wrong, library) one JSON line each. ``bench/openset_refit.py`` reads them. The source of every example is
the query file's stem's parent folder name (``/work/w/s13_x37/queries.jsonl`` -> ``s13_x37``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--store", required=True)
    p.add_argument("--queries", required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--rois", default="mask", help="ROI kinds, comma-separated (mask, box)")
    args = p.parse_args()

    from pipeline.evaluate.datasets import load_queries
    from pipeline.evaluate.library import Library, read_store_meshes
    from pipeline.evaluate.openset import YCB_VIDEO_LABELS, collect
    from pipeline.evaluate.openset_split import mesh_ids_with_labels, without_meshes
    from pipeline.query import Retriever

    path = Path(args.queries)
    source = path.parent.name if path.stem == "queries" else path.stem
    absent = set(YCB_VIDEO_LABELS)
    library = Library(read_store_meshes(args.store))
    queries = [(q, source) for q in load_queries(path)]
    with Retriever.open(args.store) as full:
        reduced = without_meshes(full, mesh_ids_with_labels(library, absent))
        examples = collect(full, reduced, queries, library, absent, tuple(args.rois.split(",")))
    with open(args.out, "w") as f:
        for e in examples:
            f.write(json.dumps(e.to_json()) + "\n")
    print(f"{source}: {len(examples)} answers -> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

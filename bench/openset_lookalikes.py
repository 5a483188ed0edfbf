"""Which library models the shipped calibration accepts for objects the library lacks (no fit, no choice).

    python bench/openset_lookalikes.py --store STORE --examples EXAMPLES.jsonl [--examples ...] \
        [--variant two-stage+verify] [--roi mask]

Reads answers written by ``bench/openset_examples.py`` (or ``python -m pipeline.evaluate openset``), scores
them with the shipped offline calibration at its operating point and prints, per absent object, how many of
its answers were accepted and the names of the models they were accepted as (with the confidence), then the
present objects whose right answers were refused. Diagnostics for docs/results.md, section 12.2.
"""

from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--store", required=True, help="the store the answers were made on (for model names)")
    p.add_argument("--examples", action="extend", nargs="+", required=True, help="one or more answer files")
    p.add_argument("--variant", default="two-stage+verify")
    p.add_argument("--roi", default="mask")
    args = p.parse_args()

    from pipeline.evaluate.library import read_store_meshes
    from pipeline.evaluate.openset import load_examples
    from pipeline.query.accept import load_calibration

    names = {m.mesh_id: m.name for m in read_store_meshes(args.store)}
    model = load_calibration("offline").variants[args.variant]
    absent: dict[str, list[tuple[str, float]]] = defaultdict(list)
    n_absent: dict[str, int] = defaultdict(int)
    refused: dict[str, list[bool]] = defaultdict(list)
    for e in load_examples(args.examples, args.variant, (args.roi,)):
        x = np.array([[e.features.get(f) for f in model.features]], np.float64)
        conf = float(model.predict(x)[0])
        if e.library != "full":
            n_absent[e.group] += 1
            if conf >= model.threshold:
                absent[e.group].append((names.get(e.top1, (e.top1 or "")[:8]), conf))
        elif e.correct:
            refused[e.group].append(conf < model.threshold)
    print(f"threshold {model.threshold}; absent object: accepted / answers, accepted as (confidence)")
    for g in sorted(n_absent):
        got = ", ".join(f"{n} ({c:.2f})" for n, c in sorted(absent[g], key=lambda t: -t[1]))
        print(f"  {g}: {len(absent[g])} / {n_absent[g]}  {got}")
    total = sum(len(v) for v in absent.values())
    print(f"  all: {total} / {sum(n_absent.values())} accepted")
    worst = {g: (sum(v), len(v)) for g, v in sorted(refused.items()) if any(v)}
    print(f"right answers refused (refused / right) by object: {worst}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

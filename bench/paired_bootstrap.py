"""Top-1 / top-5 of two evaluation runs on the same queries, with paired bootstrap intervals.

    python bench/paired_bootstrap.py A/per_query.jsonl B/per_query.jsonl [--draws 2000] [--seed 0]

Reads the ``per_query.jsonl`` that ``python -m pipeline.evaluate ... --out DIR`` writes for each run (e.g.
with and without ``--model learned_encoder=none``). The draws resample meshes (the part of a synthetic
query id before its last ``-``), so a mesh's queries stay together, and the same draw is used for both
runs: the interval of the difference is paired. Prints one line per cut-off.
"""

from __future__ import annotations

import argparse
import json
import random


def load(path: str) -> dict[str, dict]:
    with open(path, encoding="utf-8") as f:
        return {r["query_id"]: r for r in map(json.loads, f)}


def hit_rate(runs: dict[str, dict], keys: list[str], n: int) -> float:
    return sum(1 for k in keys if runs[k]["rank"] is not None and runs[k]["rank"] <= n) / len(keys)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("a")
    ap.add_argument("b")
    ap.add_argument("--draws", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    a, b = load(args.a), load(args.b)
    keys = sorted(set(a) & set(b))
    groups = sorted({k.rsplit("-", 1)[0] for k in keys})
    by_group = {g: [k for k in keys if k.rsplit("-", 1)[0] == g] for g in groups}
    rng = random.Random(args.seed)
    lo, hi = int(0.025 * args.draws), int(0.975 * args.draws) - 1

    def interval(values: list[float]) -> str:
        v = sorted(values)
        return f"[{v[lo]:.3f}, {v[hi]:.3f}]"

    print(f"{len(keys)} queries in both runs, {len(groups)} meshes")
    for n in (1, 5):
        xs, ys, ds = [], [], []
        for _ in range(args.draws):
            pick = [k for g in (rng.choice(groups) for _ in groups) for k in by_group[g]]
            x, y = hit_rate(a, pick, n), hit_rate(b, pick, n)
            xs.append(x)
            ys.append(y)
            ds.append(x - y)
        x0, y0 = hit_rate(a, keys, n), hit_rate(b, keys, n)
        print(
            f"top-{n}: A {x0:.3f} {interval(xs)}, B {y0:.3f} {interval(ys)}, "
            f"A - B {x0 - y0:+.3f} {interval(ds)}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

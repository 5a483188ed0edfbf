"""What the synthetic set's mask growth costs: two dumps of the same queries, one with exact masks.

    python bench/mask_growth.py --exact DUMP --grown DUMP

Both dumps are ``bench/learned_features.py``'s (with ``exposure_110.npz``, ``bench/learned_exposure.py
--dump-only``) of ``synth --hard`` sets made with the same store and seed, one with ``--mask-grow 0,0``
and one with the default growth of 0-4 px, so their images are the same and only the query masks differ.
Printed per cue (the shipped learned cue alone, the descriptor alone, the shipped fusion with
verification): top-1 / top-5 on each, and the paired difference with a 95 % bootstrap interval over
objects. Results: docs/results.md, section 10.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

import learned_ltr as ltr  # noqa: E402
from learned_fusion import bootstrap, ranks_of  # noqa: E402


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--exact", required=True, help="the dump of the set with exact masks")
    p.add_argument("--grown", required=True, help="the dump of the same set with grown masks")
    args = p.parse_args()
    X, G = ltr.load(Path(args.exact)), ltr.load(Path(args.grown))
    if [r["query_id"] for r in X["recs"]] != [r["query_id"] for r in G["recs"]]:
        raise SystemExit("the two dumps do not hold the same queries")
    cues = {
        "learned cue alone": lambda D: ranks_of(D["L"]["shipped"], D["exp"]),
        "descriptor alone": lambda D: ranks_of(D["desc"], D["exp"]),
        "shipped fusion + verification": ltr.shipped,
    }
    for name, ranks in cues.items():
        rx, rg = ranks(X), ranks(G)
        for k in (1, 5):
            d = (rx <= k).astype(float) - (rg <= k).astype(float)
            lo, hi = bootstrap(d, X["label"])
            print(
                f"{name}: top-{k} exact {np.mean(rx <= k):.3f}, grown {np.mean(rg <= k):.3f}, "
                f"difference {d.mean():+.3f} [{lo:+.3f}, {hi:+.3f}]"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

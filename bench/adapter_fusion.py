"""Fit the fusion weights the ranking uses with a store's query adapter, on synthetic dumps only.

    python bench/adapter_fusion.py --store STORE --train SYNTH_DUMP [--train ...] --test PHOTO_DUMP \
        [--confirm FRESH_SYNTH_DUMP]

STORE: a store onboarded with probes (its ``adapters`` row is read as a query reads it). The dumps are
``bench/learned_features.py``'s with ``bench/learned_exposure.py``'s ``exposure_110.npz`` (the shipped cue),
made against a store with the same views. Each dump's ROI vectors go through the store's adapter; the shipped
cue set (``raw4``: learned, descriptor, ROI caption, prompt, plus verification) is refitted with the adapted
learned cosine by ``bench/learned_ltr.py``'s listwise fit on the ``--train`` dumps (none of their images is a
probe: probes are made from the stored views). Printed: the fitted weights (the ``adapter_fuse_*`` query
settings), and top-1 / top-5 without -> with the adapter on the test and confirm dumps, each ranked by its
own refit (95 % intervals, paired, by photo or object). The photos are never fitted or chosen on.
Results: docs/results.md, section 11.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

import learned_adapter as la  # noqa: E402
import learned_ltr as ltr  # noqa: E402
from learned_fusion import ranks_of  # noqa: E402


def store_adapter(store_path: str) -> np.ndarray:
    """The matrix a query on ``store_path`` would apply (exits when the store has none that matches)."""
    from pipeline.query import Retriever

    with Retriever.open(store_path, preload=False) as r:
        adapter = r.tables.adapter
        if adapter is None:
            raise SystemExit(
                f"store {store_path} has no query adapter that matches its models (onboard with probes)"
            )
        print(f"adapter of run {adapter.run_id}: {adapter.n_probes} probes of {adapter.n_models} models")
        return adapter.matrix


def adapted_scores(D: dict, matrix: np.ndarray) -> np.ndarray:
    """(queries, models): each model's best-view cosine with the adapted ROI vectors (the query's rule)."""
    from pipeline.adapter.fit import apply_adapter

    q = apply_adapter(D["R"], matrix)
    s = q @ D["V"].T
    out = np.full((len(q), int(D["vm"].max()) + 1), -np.inf, np.float32)
    for m in range(out.shape[1]):
        out[:, m] = s[:, D["vm"] == m].max(axis=1)
    return out


def main() -> int:
    from pipeline.evaluate.library import read_store_meshes

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--store", required=True)
    p.add_argument("--train", action="append", required=True, help="a synthetic dump (repeatable)")
    p.add_argument("--test", required=True, help="the photos' dump (never fitted or chosen on)")
    p.add_argument("--confirm", help="a fresh synthetic dump sharing no image with --train")
    args = p.parse_args()
    matrix = store_adapter(args.store)
    label = {m.mesh_id: m.name[:3] for m in read_store_meshes(args.store)}
    T = [la.loaded(Path(d), label) for d in args.train]
    tests = [("photos", la.loaded(Path(args.test), label), "photo")]
    if args.confirm:
        tests.append((Path(args.confirm).name, la.loaded(Path(args.confirm), label), "label"))
    for D in (*T, *(D for _, D, _ in tests)):
        D["AD"] = adapted_scores(D, matrix)
    cues = {
        "plain": lambda D: [D["L"]["shipped"], *ltr.FEATSETS["raw4"](D)[1:]],
        "adapted": lambda D: [D["AD"], *ltr.FEATSETS["raw4"](D)[1:]],
    }
    ranks = {}
    for name, fn in cues.items():
        w, wv = ltr.fit_all(T, fn)
        print(
            f"{name}: weights learned {w[0]:.3f}, descriptor {w[1]:.3f}, ROI caption {w[2]:.3f}, "
            f"prompt {w[3]:.3f}, verification {wv:.3f}"
        )
        for tname, D, _ in tests:
            ranks[name, tname] = ranks_of(ltr.scores(np.stack(fn(D)), w, ltr.bonus(D), wv), D["exp"])
    print("top-1 / top-5, plain -> adapted (each with its own refit):")
    for tname, D, group in tests:
        print(f"   {tname}: {la.per_kind(D, ranks['adapted', tname], ranks['plain', tname], D[group])}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Choose the learned encoder's pooling / input size / flip / ROI framing and the score fusion by cross-validation.

    python bench/learned_fusion.py --feats DIR [--folds photo|object] [--json OUT]

Reads what ``bench/learned_features.py`` dumped (per query and mesh: descriptor, text and inlier scores; the
learned features of views and ROIs). Every setting of the grid below is scored on the queries of the
training folds; the best one (top-1 + top-5 / 2, ties to the simpler setting) ranks the held-out fold.
Folds: leave one photo out (default) or leave one object out. Both query kinds (mask and box) are pooled.
Prints the held-out top-1 / top-5 per kind with 95% bootstrap intervals (photos resampled), the setting
each fold chose, the setting chosen on all queries, and per-object held-out ranks. ``--ensembles`` adds
the mean of two CLS variants' learned scores at different input sizes to the settings searched.

The fused score of a mesh (:mod:`pipeline.query.fusion`) is

    score = (1 - w_desc - w_text) * learned + w_desc * descriptor + w_text * text + verify bonus

(cosines, the learned and descriptor ones max over the mesh's views; the bonus is added to the top
``VERIFY_TOP`` by the rest of the score, as at query time).
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

VERIFY_TOP = 20
INLIER_FLOOR, INLIER_CAP = 4, 20
TAU = 0.45


def l2(x):
    return x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-12)


def learned_scores(
    feats: Path, size: int, flip: int, pool: str, n_meshes: int, margin: int = 0
) -> np.ndarray:
    """(queries, meshes): max over a mesh's views of the ROI-view cosine (the ROI framed with ``margin``
    percent of render gray when non-zero, ``bench/learned_features.py --roi-margins``)."""
    a = np.load(feats / f"feat_{size}_0.npz")
    views, rois = l2(a[f"views_{pool}"]), l2(a[f"rois_{pool}"])
    if margin:
        rois = l2(np.load(feats / f"rois_m{margin}_{size}.npz")[f"rois_{pool}"])
    if flip:
        b = np.load(feats / f"feat_{size}_1.npz")
        views, rois = l2(views + l2(b[f"views_{pool}"])), l2(rois + l2(b[f"rois_{pool}"]))
    return best_per_model(rois @ views.T, a["view_mesh"], n_meshes)


def cosine_per_model(rois: np.ndarray, views: np.ndarray, view_mesh: np.ndarray, n_meshes: int) -> np.ndarray:
    """(queries, meshes): each mesh's best view by the cosine of the ROI and view feature rows."""
    return best_per_model(l2(rois) @ l2(views).T, view_mesh, n_meshes)


def best_per_model(s: np.ndarray, view_mesh: np.ndarray, n_meshes: int) -> np.ndarray:
    """(queries, meshes) from (queries, views) scores: each mesh's best view (``view_mesh``: each view's
    mesh index; every mesh must have a view)."""
    out = np.full((len(s), n_meshes), -1.0, s.dtype)
    for j in range(n_meshes):
        out[:, j] = s[:, view_mesh == j].max(axis=1)
    return out


def parts(key) -> list[tuple]:
    """The (size, flip, pooling, margin) variants of a learned key: itself, or an ensemble's members."""
    return list(key) if isinstance(key[0], tuple) else [key]


def key_simplicity(key) -> float:
    """Fewer members, no flip, no framing, smaller inputs first (the tie-break between settings)."""
    return sum(flip + (margin > 0) + size / 1000 for size, flip, _, margin in parts(key)) + len(parts(key)) - 1


def describe_key(key) -> dict:
    """A learned key as the JSON output shows it (an ensemble: its members under ``ensemble``)."""
    members = [
        {"size": size, "flip": bool(flip), "pooling": pool, "roi_margin_pct": margin}
        for size, flip, pool, margin in parts(key)
    ]
    return members[0] if len(members) == 1 else {"ensemble": members}


def dumped_cues(recs: list[dict]):
    """(descriptor, text, inliers, expected mesh indices, ROI kind, photo) of the dumped query records."""
    desc = np.array([r["desc"] for r in recs], np.float32)
    text = np.array([r["text"] for r in recs], np.float32)
    inl = np.array([r["inliers"] for r in recs], np.float32)
    kind = np.array([r["kind"] for r in recs])
    photo = np.array([r["photo"] for r in recs])
    return desc, text, inl, [r["expected"] for r in recs], kind, photo


def hit_rates(ranks: np.ndarray, groups: np.ndarray) -> dict:
    """Top-1 / top-5 of ``ranks`` with 95 % bootstrap intervals resampling ``groups`` (photos)."""
    t1, t5 = (ranks <= 1).astype(float), (ranks <= 5).astype(float)
    return {
        "top1": round(t1.mean(), 3),
        "top1_ci": [round(v, 3) for v in bootstrap(t1, groups)],
        "top5": round(t5.mean(), 3),
        "top5_ci": [round(v, 3) for v in bootstrap(t5, groups)],
    }


def ranks_of(score: np.ndarray, expected: list[list[int]]) -> np.ndarray:
    r = np.empty(len(score), np.int64)
    for i, exp in enumerate(expected):
        order = np.argsort(-score[i], kind="stable")
        pos = np.empty_like(order)
        pos[order] = np.arange(len(order))
        r[i] = 1 + min(pos[e] for e in exp)
    return r


def fuse(learned, desc, text, inl, w_desc, w_text, w_verify, stage1):
    base = (1 - w_desc - w_text) * learned + w_desc * desc + w_text * text
    if stage1 is not None:
        base = np.where(stage1, base, base - 10.0)  # candidates outside stage 1 rank last
    if w_verify > 0:
        bonus = w_verify * np.clip((inl - INLIER_FLOOR) / (INLIER_CAP - INLIER_FLOOR), 0, 1)
        top = np.argsort(-base, axis=1)[:, :VERIFY_TOP]
        mask = np.zeros_like(base, bool)
        np.put_along_axis(mask, top, True, axis=1)
        base = base + np.where(mask, bonus, 0.0)
    return base


def stage1_mask(text: np.ndarray) -> np.ndarray:
    m = text >= TAU
    for i in np.flatnonzero(~m.any(axis=1)):
        m[i, np.argsort(-text[i])[:10]] = True
    return m


def bootstrap(hits: np.ndarray, groups: np.ndarray, n: int = 2000, seed: int = 0) -> tuple[float, float]:
    rng = np.random.default_rng(seed)
    ug = np.unique(groups)
    by = [hits[groups == g] for g in ug]
    vals = []
    for _ in range(n):
        pick = rng.integers(0, len(ug), len(ug))
        vals.append(np.concatenate([by[k] for k in pick]).mean())
    return float(np.percentile(vals, 2.5)), float(np.percentile(vals, 97.5))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--feats", required=True)
    p.add_argument("--folds", choices=("photo", "object"), default="photo")
    p.add_argument("--sizes", default=None, help="input sizes to consider (default: every dumped one)")
    p.add_argument(
        "--weights",
        choices=("spread", "grid"),
        default="spread",
        help="spread (default): the three cosines weighted by 1 / their mean spread over the library, "
        "measured on the training folds without labels (no fitted weight); grid: weights searched too",
    )
    p.add_argument(
        "--guard",
        action="append",
        default=[],
        help="(repeatable) another feature dump (e.g. a synthetic query set, bench/learned_features.py --kinds mask) "
        "that a setting must not do worse on than --guard-ref: settings whose top-1 or top-5 there falls "
        "below the reference's are left out of the cross-validation (spread weights only)",
    )
    p.add_argument(
        "--guard-ref",
        default="224,0,cls,0,0.3",
        help="the reference setting size,flip,pooling,margin%%,w_verify (default: the setting shipped before "
        "the guard existed)",
    )
    p.add_argument(
        "--ensembles",
        action="store_true",
        help="also consider the mean of two variants' learned scores (CLS pooling, different input sizes): "
        "two learned embeddings per view and per ROI (spread weights only)",
    )
    p.add_argument("--json")
    args = p.parse_args()
    if args.ensembles and args.weights != "spread":
        p.error("--ensembles needs --weights spread")
    feats = Path(args.feats)
    recs = json.loads((feats / "queries.json").read_text())
    n_meshes = len(json.loads((feats / "meshes.json").read_text()))
    desc, text, inl, expected, kind, photo = dumped_cues(recs)
    label = np.array([r["label"] for r in recs])
    groups = photo if args.folds == "photo" else label
    s1 = stage1_mask(text)
    sizes = sorted({int(f.stem.split("_")[1]) for f in feats.glob("feat_*_0.npz")})
    if args.sizes:
        sizes = [s for s in sizes if s in {int(x) for x in args.sizes.split(",")}]
    learned = {
        (size, flip, pool, 0): learned_scores(feats, size, flip, pool, n_meshes)
        for size in sizes
        for flip in (0, 1)
        if (feats / f"feat_{size}_{flip}.npz").exists()
        for pool in ("cls", "mean", "patch")
    }
    for f in sorted(feats.glob("rois_m*_*.npz")):  # ROI framings, unflipped
        margin, size = (int(v) for v in f.stem[len("rois_m") :].split("_"))
        if size in sizes:
            for pool in ("cls", "mean", "patch"):
                learned[(size, 0, pool, margin)] = learned_scores(feats, size, 0, pool, n_meshes, margin)
    if args.ensembles:
        singles = [k for k in learned if k[2] == "cls" and k[1] == 0]
        for a, b in itertools.combinations(singles, 2):
            if a[0] != b[0]:
                learned[(a, b)] = (learned[a] + learned[b]) / 2
    steps = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6)
    if args.weights == "spread":
        return spread_cv(args, recs, learned, desc, text, inl, expected, kind, photo, groups, s1)
    grid = [
        g
        for g in itertools.product(
            learned,
            steps,  # w_desc
            steps,  # w_text
            (0.0, 0.1, 0.2, 0.3),  # w_verify
            (False, True),  # stage-1 filter
        )
        if g[1] + g[2] <= 0.9 + 1e-9  # the learned cosine keeps at least 0.1
    ]
    # every setting's rank of every query, once
    table = np.stack(
        [
            ranks_of(fuse(learned[lk], desc, text, inl, wd, wt, wv, s1 if f else None), expected)
            for lk, wd, wt, wv, f in grid
        ]
    )

    def simplicity(g):  # fewer non-zero weights, no flip, smaller input first
        (size, flip, _, margin), wd, wt, wv, f = g
        return (wd > 0) + (wt > 0) + (wv > 0) + flip + f + (margin > 0) + size / 1000

    def best(sel: np.ndarray) -> int:
        r = table[:, sel]
        obj = (r <= 1).mean(axis=1) + 0.5 * (r <= 5).mean(axis=1)
        top = np.flatnonzero(obj >= obj.max() - 1e-9)
        return int(min(top, key=lambda k: simplicity(grid[k])))

    held = np.zeros(len(recs), np.int64)
    chosen = {}
    for g in np.unique(groups):
        test = groups == g
        k = best(~test)
        held[test] = table[k, test]
        chosen[str(g)] = describe(grid[k])
    final = best(np.ones(len(recs), bool))
    out = {"folds": args.folds, "chosen_per_fold": chosen, "chosen_on_all": describe(grid[final])}
    for kd in ("mask", "box"):
        sel = kind == kd
        summary = {}
        for name, r in (("held_out", held[sel]), ("chosen_on_all_in_sample", table[final, sel])):
            summary[name] = hit_rates(r, photo[sel])
        for ref_name, ref in (
            ("learned_only_224_cls", learned[(sizes[0], 0, "cls", 0)] if sizes else None),
            ("descriptor_only", desc),
        ):
            if ref is None:
                continue
            r = ranks_of(ref, expected)[sel]
            summary[ref_name] = {"top1": round((r <= 1).mean(), 3), "top5": round((r <= 5).mean(), 3)}
        summary["per_object_held_out_rank"] = {
            f"{recs[i]['query_id']}": int(held[i]) for i in np.flatnonzero(sel)
        }
        out[kd] = summary
    print(json.dumps(out, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


def spread_weights(learned, desc, text, sel) -> tuple[float, float, float]:
    """(learned, descriptor, text) weights proportional to 1 / each score's mean per-query spread over the
    meshes of the queries ``sel`` (label-free: each cue moves the fused score about as much as the others)."""
    inv = np.array([1 / x[sel].std(axis=1).mean() for x in (learned, desc, text)])
    w = inv / inv.sum()
    return float(w[0]), float(w[1]), float(w[2])


def guard_filter(args, grid, learned, desc, text, guard: str) -> tuple[list, dict]:
    """The settings of ``grid`` that do no worse than ``--guard-ref`` on the ``guard`` set (top-1 and
    top-5, with the spread weights of the main set's queries), and each setting's guard scores."""
    gdir = Path(guard)
    grecs = json.loads((gdir / "queries.json").read_text())
    n_meshes = len(json.loads((gdir / "meshes.json").read_text()))
    gdesc, gtext, ginl, gexp, _, _ = dumped_cues(grecs)
    allq = np.ones(len(desc), bool)
    cache: dict = {}

    def scores_of(key):
        for m in parts(key):
            if m not in cache:
                cache[m] = learned_scores(gdir, m[0], m[1], m[2], n_meshes, m[3])
        return np.mean([cache[m] for m in parts(key)], axis=0)

    def rates(g):
        key, wv = g
        _, wd, wt = spread_weights(learned[key], desc, text, allq)
        r = ranks_of(fuse(scores_of(key), gdesc, gtext, ginl, wd, wt, wv, None), gexp)
        return float((r <= 1).mean()), float((r <= 5).mean())

    size, flip, pool, margin, wv = args.guard_ref.split(",")
    ref = rates(((int(size), int(flip), pool, int(margin)), float(wv)))
    scores, keep = {}, []
    for g in grid:
        needed = [
            name
            for size, flip, _, margin in parts(g[0])
            for name in [f"feat_{size}_0.npz"]
            + [f"feat_{size}_1.npz"] * flip
            + [f"rois_m{margin}_{size}.npz"] * bool(margin)
        ]
        if not all((gdir / name).exists() for name in needed):
            continue  # not dumped for the guard set
        t1, t5 = rates(g)
        scores[str(g)] = (round(t1, 3), round(t5, 3))
        if t1 >= ref[0] - 1e-9 and t5 >= ref[1] - 1e-9:
            keep.append(g)
    return keep, {"reference": args.guard_ref, "reference_top1_top5": ref, "kept": len(keep), "of": len(grid),
                  "scores": scores}  # fmt: skip


def spread_cv(args, recs, learned, desc, text, inl, expected, kind, photo, groups, s1) -> int:
    """Cross-validation with spread weights: only the learned variant and the verification weight are chosen."""
    grid = list(itertools.product(learned, (0.0, 0.1, 0.2, 0.3)))
    guard = {}
    for gdir in args.guard:
        grid, guard[gdir] = guard_filter(args, grid, learned, desc, text, gdir)

    def ranks(g, sel):
        wv, L = g[1], learned[g[0]]
        wl, wd, wt = spread_weights(L, desc, text, sel)
        return ranks_of(fuse(L, desc, text, inl, wd, wt, wv, None), expected), (wl, wd, wt)

    def best(sel):
        scored = []
        for k, g in enumerate(grid):
            r = ranks(g, sel)[0][sel]
            simple = (g[1] > 0) + key_simplicity(g[0])
            scored.append((-((r <= 1).mean() + 0.5 * (r <= 5).mean()), simple, k))
        return min(scored)[2]

    held = np.zeros(len(recs), np.int64)
    chosen = {}
    for gname in np.unique(groups):
        test = groups == gname
        k = best(~test)
        r, w = ranks(grid[k], ~test)
        held[test] = r[test]
        chosen[str(gname)] = {
            **describe_key(grid[k][0]),
            "w_verify": grid[k][1],
            "weights_learned_desc_text": [round(x, 3) for x in w],
        }
    allq = np.ones(len(recs), bool)
    k = best(allq)
    r_all, w_all = ranks(grid[k], allq)
    out = {
        "folds": args.folds,
        "weights": "spread",
        "guard": guard,
        "chosen_per_fold": chosen,
        "chosen_on_all": {
            **describe_key(grid[k][0]),
            "w_verify": grid[k][1],
            "weights_learned_desc_text": [round(x, 3) for x in w_all],
        },
    }
    for kd in ("mask", "box"):
        sel = kind == kd
        summary = {}
        for name, r in (("held_out", held[sel]), ("chosen_on_all_in_sample", r_all[sel])):
            summary[name] = hit_rates(r, photo[sel])
        summary["per_object_held_out_rank"] = {recs[i]["query_id"]: int(held[i]) for i in np.flatnonzero(sel)}
        out[kd] = summary
    print(json.dumps(out, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


def describe(g) -> dict:
    (size, flip, pool, margin), wd, wt, wv, f = g
    return {
        "size": size,
        "flip": bool(flip),
        "pooling": pool,
        "roi_margin_pct": margin,
        "w_desc": wd,
        "w_text": wt,
        "w_verify": wv,
        "stage1_filter": bool(f),
    }


if __name__ == "__main__":
    raise SystemExit(main())

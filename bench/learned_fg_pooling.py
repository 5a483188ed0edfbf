"""Foreground-only poolings of the learned encoder's patch tokens, and per-query fusions, scored on a dump.

    python bench/learned_features.py --store STORE --queries Q.jsonl --out DIR     # first (the dump)
    python bench/learned_fg_pooling.py --feats DIR --store STORE [--size 224]

The shipped learned score pools the CLS token (bench/learned_fusion.py chose it); the mean of *all* patch
tokens scored far lower on real photos because the gray background patches, alike in every view and ROI,
dominate it. This script pools only the foreground patches (pixels off the render gray, per 14 px patch)
of every stored view and ROI: their mean (``fgmean``), the mean weighted by the foreground share (``fgw``),
GeM (p = 3) and max. It then ranks with each pooling alone and fused as at query time (spread weights,
verification bonus), and also tries per-query fusions of z-scored cues (equal weights, weighted by each
cue's top z-score or top-2 gap, reciprocal-rank fusion), choosing among all by leave-one-photo-out
cross-validation. Prints one line per setting and the held-out top-1 / top-5 with bootstrap intervals.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from PIL import Image

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from learned_features import dump_rois, view_images  # noqa: E402
from learned_fusion import (  # noqa: E402
    INLIER_CAP,
    INLIER_FLOOR,
    bootstrap,
    dumped_cues,
    l2,
    ranks_of,
    spread_weights,
)

POOLS = ("cls", "fgmean", "fgw", "fggem", "fgmax")


def foreground_share(im, fill: tuple[int, int, int], size: int) -> np.ndarray:
    """Per 14 px patch of ``im`` as the encoder sees it (square on ``fill``, ``size`` px), the share of its
    pixels off the render gray, in token order."""
    from pipeline.models.focus_encoder import square_on

    g = size // 14
    sq = square_on(im, tuple(fill)).resize((size, size), Image.Resampling.BILINEAR)
    fg = (np.abs(np.asarray(sq, np.float32) - np.array(fill, np.float32)).sum(-1) > 8).astype(np.float32)
    return fg.reshape(g, 14, g, 14).mean(axis=(1, 3)).reshape(-1)


def pooled_features(images, enc, size: int) -> dict[str, np.ndarray]:
    out = {k: [] for k in POOLS}
    for i in range(0, len(images), 32):
        batch = images[i : i + 32]
        for im, t in zip(batch, enc.tokens(batch), strict=True):
            w = foreground_share(im, enc.fill, size)
            p, sel = t[1:], w > 0.5
            if sel.sum() < 2:
                sel = w >= w.max() - 1e-6
            out["cls"].append(t[0])
            out["fgmean"].append(p[sel].mean(0))
            out["fgw"].append((p * w[:, None]).sum(0) / max(w.sum(), 1e-6))
            out["fgmax"].append(p[sel].max(0))
            out["fggem"].append((np.clip(p[sel], 1e-6, None) ** 3).mean(0) ** (1 / 3))
    return {k: np.stack(v) for k, v in out.items()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--feats", required=True, help="the folder bench/learned_features.py wrote")
    ap.add_argument("--store", required=True)
    ap.add_argument("--size", type=int, default=224)
    args = ap.parse_args()
    from pipeline.models.focus_encoder import LearnedViewEncoder

    feats = Path(args.feats)
    recs = json.loads((feats / "queries.json").read_text())
    meshes = json.loads((feats / "meshes.json").read_text())
    nm = len(meshes)
    cache = feats / f"fg_{args.size}.npz"
    if not cache.exists():
        enc = LearnedViewEncoder(size=args.size)
        keys, views = view_images(args.store, meshes)
        rois = dump_rois(feats, recs)
        pv, pr = pooled_features(views, enc, args.size), pooled_features(rois, enc, args.size)
        np.savez(
            cache,
            view_mesh=np.array([m for m, _ in keys]),
            **{f"views_{k}": v for k, v in pv.items()},
            **{f"rois_{k}": v for k, v in pr.items()},
        )
    a = np.load(cache)
    vm = a["view_mesh"]
    desc, text, inl, expected, kind, photo = dumped_cues(recs)
    every = np.ones(len(recs), bool)

    def per_mesh(s):
        out = np.full((len(s), nm), -1.0, np.float32)
        for j in range(nm):
            out[:, j] = s[:, vm == j].max(1)
        return out

    learned = {k: per_mesh(l2(a[f"rois_{k}"]) @ l2(a[f"views_{k}"]).T) for k in POOLS}

    def z(x):
        return (x - x.mean(1, keepdims=True)) / np.maximum(x.std(1, keepdims=True), 1e-9)

    def bonus(base, wv):
        b = wv * np.clip((inl - INLIER_FLOOR) / (INLIER_CAP - INLIER_FLOOR), 0, 1)
        top = np.argsort(-base, axis=1)[:, :20]
        m = np.zeros_like(base, bool)
        np.put_along_axis(m, top, True, 1)
        return base + np.where(m, b, 0)

    def fused(name, L, p, wv):
        cues = [L, desc, text]
        if name == "spread":
            wl, wd, wt = spread_weights(L, desc, text, every)
            return bonus(wl * L + wd * desc + wt * text, wv)
        Z = [z(c) for c in cues]
        if name == "zsum":
            base = sum(Z) / 3
        elif name == "zpeak":
            w = [np.maximum(zz.max(1, keepdims=True), 1e-3) ** p for zz in Z]
            base = sum(wi * zz for wi, zz in zip(w, Z, strict=True)) / sum(w)
        elif name == "zgap":
            w = []
            for zz in Z:
                s = -np.sort(-zz, 1)
                w.append(np.maximum(s[:, :1] - s[:, 1:2], 1e-3) ** p)
            base = sum(wi * zz for wi, zz in zip(w, Z, strict=True)) / sum(w)
        else:  # reciprocal-rank fusion
            base = sum(1.0 / (p + np.argsort(np.argsort(-c, 1), 1)) for c in cues)
        return bonus(base / np.maximum(base.std(1, keepdims=True), 1e-9) * 0.1, wv)

    for k, L in learned.items():
        r = ranks_of(L, expected)
        m, b = r[kind == "mask"], r[kind == "box"]
        print(
            f"learned alone {k:7s} mask {np.mean(m <= 1):.3f}/{np.mean(m <= 5):.3f}  box {np.mean(b <= 1):.3f}/{np.mean(b <= 5):.3f}"
        )
    methods = [
        ("spread", [0]),
        ("zsum", [0]),
        ("zpeak", [0.5, 1, 2]),
        ("zgap", [0.5, 1, 2]),
        ("rrf", [1, 5, 20]),
    ]
    grid = [(n, k, p, wv) for n, ps in methods for k in learned for p in ps for wv in (0.0, 0.1, 0.3)]
    table = np.stack([ranks_of(fused(n, learned[k], p, wv), expected) for n, k, p, wv in grid])
    for g, r in zip(grid, table, strict=True):
        m, b = r[kind == "mask"], r[kind == "box"]
        print(
            f"fused {str(g):34s} mask {np.mean(m <= 1):.3f}/{np.mean(m <= 5):.3f}  box {np.mean(b <= 1):.3f}/{np.mean(b <= 5):.3f}"
        )
    held = np.zeros(len(recs), int)
    for ph in np.unique(photo):
        test = photo == ph
        score = (table[:, ~test] <= 1).mean(1) + 0.5 * (table[:, ~test] <= 5).mean(1)
        k = int(np.argmax(score))
        held[test] = table[k, test]
        print(f"fold {ph}: chose {grid[k]}")
    for kd in ("mask", "box"):
        s = kind == kd
        t1, t5 = (held[s] <= 1).astype(float), (held[s] <= 5).astype(float)
        lo1, hi1 = bootstrap(t1, photo[s])
        lo5, hi5 = bootstrap(t5, photo[s])
        print(
            f"held out ({kd}): top-1 {t1.mean():.3f} [{lo1:.2f}, {hi1:.2f}], top-5 {t5.mean():.3f} [{lo5:.2f}, {hi5:.2f}]"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

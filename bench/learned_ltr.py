"""A linear fusion learned on synthetic feature dumps (listwise softmax), tested on the labelled photos.

    python bench/learned_ltr.py --train SYNTH_DUMP [--train DIR ...] --test PHOTO_DUMP

The ``raw4`` fit (rounded) is the shipped fusion (docs/results.md, section 7.2): the set the selection rule
printed last picks (the simplest, ``raw3``, unless another beats it held out with a paired interval above 0). The dumps are ``bench/learned_features.py``'s (224 px,
unflipped). Their learned cues are the last block's; the shipped fusion (the "shipped" lines) pools block 11
(docs/results.md, section 7.3) of images whose foreground is normalised to one exposure (section 7.4), read
from ``bench/learned_exposure.py``'s ``exposure_110.npz`` in each dump (run that bench on a dump first). For each feature set the weights (cues, verification bonus, a temperature) maximise the mean
log-probability of the right mesh under a softmax over the library, on the training dumps only. Printed:
the shipped fusion's top-1 / top-5 on every dump; per feature set the fitted weights (normalised to
sum |w| = 1), the training dumps' held-out numbers (5 folds by object label) and the photos' (never used
to fit). Intervals: 95 % bootstrap over objects (training dumps) or photos (the test dump).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import minimize

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from learned_fusion import (  # noqa: E402
    INLIER_CAP,
    INLIER_FLOOR,
    VERIFY_TOP,
    bootstrap,
    cosine_per_model,
    dumped_cues,
    fuse,
    learned_scores,
    ranks_of,
)

SIMPLEST = "raw3"  # the cues of stage 1's score (learned, descriptor, text)
SHIPPED = "raw4"  # the cues pipeline.query.fusion weighs (learned, descriptor, ROI-caption text, prompt text)


def shipped_weights() -> tuple[float, float, float, float]:
    """The offline profile's fusion weights (descriptor, ROI-caption text, prompt text, verification)."""
    from pipeline.query.settings import settings_for

    s = settings_for("offline")
    return s.fuse_desc, s.fuse_text, s.fuse_prompt, s.fuse_verify_weight


def shipped_block() -> int | None:
    """The block the offline profile's learned encoder pools (``None``: the last)."""
    from pipeline.profiles import get_profile

    return get_profile("offline").learned_encoder.options.get("layer")


def shipped_exposure() -> float | None:
    """The foreground luminance the offline profile's learned encoder normalises to (``None``: off)."""
    from pipeline.profiles import get_profile

    return get_profile("offline").learned_encoder.options.get("exposure") or None


def exposure_scores(d: Path, target: float, n: int) -> np.ndarray | None:
    """(queries, models): best cosine over a model's views of the shipped block's CLS on images normalised
    to ``target`` (``bench/learned_exposure.py``'s ``exposure_<target>.npz``); ``None`` when not dumped."""
    path = d / f"exposure_{target:g}.npz"
    if not path.exists():
        return None
    a = np.load(path)
    return cosine_per_model(a["rois"], a["views"], a["view_mesh"], n)


def block_scores(d: Path, block: int, n: int) -> np.ndarray | None:
    """(queries, models): best cosine over a model's views of block ``block``'s CLS token (1-based), from
    ``bench/learned_layers.py``'s ``layers_224.npz`` in the dump; ``None`` when the dump has none."""
    path = d / "layers_224.npz"
    if not path.exists():
        return None
    a = np.load(path)
    return cosine_per_model(a["rois"][block - 1], a["views"][block - 1], a["view_mesh"], n)


def load(d: Path):
    """A dump's cues. ``L["cls"]`` is the last block's CLS cosine (as ``bench/learned_features.py`` dumps it);
    ``L["shipped"]`` the shipped block's (the same when the profile pools the last block)."""
    recs = json.loads((d / "queries.json").read_text())
    n = len(json.loads((d / "meshes.json").read_text()))
    desc, text, inl, exp, kind, photo = dumped_cues(recs)
    L = {p: learned_scores(d, 224, 0, p, n) for p in ("cls", "mean", "patch")}
    block, exposure = shipped_block(), shipped_exposure()
    if exposure is not None:
        L["shipped"] = exposure_scores(d, exposure, n)
    else:
        L["shipped"] = L["cls"] if block is None else block_scores(d, block, n)
    troi = np.array([r["text_roi"] for r in recs], np.float32)
    tpr = np.array([r["text_prompt"] for r in recs], np.float32)
    label = np.array([r["label"] for r in recs])
    return dict(
        recs=recs,
        desc=desc,
        text=text,
        troi=troi,
        tpr=tpr,
        inl=inl,
        exp=exp,
        kind=kind,
        photo=photo,
        label=label,
        L=L,
    )


def z(x):
    """Each query's scores in standard deviations about its mean over the library."""
    return (x - x.mean(axis=1, keepdims=True)) / np.maximum(x.std(axis=1, keepdims=True), 1e-6)


FEATSETS = {
    "raw3": lambda D: [D["L"]["cls"], D["desc"], D["text"]],
    "z3": lambda D: [z(D["L"]["cls"]), z(D["desc"]), z(D["text"])],
    "raw4": lambda D: [D["L"]["cls"], D["desc"], D["troi"], D["tpr"]],
    "z4": lambda D: [z(D["L"]["cls"]), z(D["desc"]), z(D["troi"]), z(D["tpr"])],
    "z6": lambda D: [z(D["L"]["cls"]), z(D["L"]["patch"]), z(D["desc"]), z(D["troi"]), z(D["tpr"])],
    "rawz": lambda D: [D["L"]["cls"], D["desc"], D["text"], z(D["L"]["cls"]), z(D["desc"]), z(D["text"])],
}


def bonus(D):
    return np.clip((D["inl"] - INLIER_FLOOR) / (INLIER_CAP - INLIER_FLOOR), 0, 1)


def scores(F, w, b, wv):
    base = np.tensordot(w, F, axes=1)
    top = np.argsort(-base, axis=1)[:, :VERIFY_TOP]
    m = np.zeros_like(base, bool)
    np.put_along_axis(m, top, True, axis=1)
    return base + np.where(m, wv * b, 0.0)


def fit(Fs, bs, exps, lam=1e-3):
    """Cue weights and verification weight (sum |w| = 1) maximising the right mesh's softmax log-probability."""
    F = np.concatenate(Fs, axis=1)  # (k, Q, M)
    b = np.concatenate(bs, axis=0)
    exp = sum(exps, [])
    k = F.shape[0]

    def loss(p):
        w, wv, t = p[:k], p[k], np.exp(p[k + 1])
        s = (np.tensordot(w, F, axes=1) + wv * b) * t
        s = s - s.max(axis=1, keepdims=True)
        lse = np.log(np.exp(s).sum(axis=1))
        pos = np.array([np.log(np.exp(s[i, e]).sum()) for i, e in enumerate(exp)])
        return (lse - pos).mean() + lam * (w @ w)

    p0 = np.r_[np.ones(k) / k, 0.3, np.log(20.0)]
    r = minimize(loss, p0, method="L-BFGS-B")
    w, wv = r.x[:k], r.x[k]
    s = np.abs(w).sum()
    return w / s, wv / s


def cv_ranks(trains: list[dict], fn, k: int = 5) -> list[np.ndarray]:
    """Held-out ranks of every training dump's queries under feature set ``fn``: ``k`` folds by object
    label (one shuffle, seed 0), each fold ranked by weights fitted on the other folds of every dump."""
    labels = np.unique(np.concatenate([D["label"] for D in trains]))
    rng = np.random.default_rng(0)
    folds = {lab: i % k for i, lab in enumerate(rng.permutation(labels))}
    held = [np.zeros(len(D["recs"]), int) for D in trains]
    for f in range(k):
        Fs, bs, exps = [], [], []
        for D in trains:
            tr = np.array([folds[x] != f for x in D["label"]])
            Fs.append(np.stack(fn(D))[:, tr])
            bs.append(bonus(D)[tr])
            exps.append([e for e, t in zip(D["exp"], tr, strict=True) if t])
        w, wv = fit(Fs, bs, exps)
        for D, h in zip(trains, held, strict=True):
            te = np.array([folds[x] == f for x in D["label"]])
            h[te] = ranks_of(scores(np.stack(fn(D)), w, bonus(D), wv), D["exp"])[te]
    return held


def fit_all(trains: list[dict], fn) -> tuple[np.ndarray, float]:
    """Feature set ``fn``'s weights fitted on every training dump (the weights a fusion would ship)."""
    return fit([np.stack(fn(D)) for D in trains], [bonus(D) for D in trains], [D["exp"] for D in trains])


def rates(r, groups):
    t1, t5 = (r <= 1).astype(float), (r <= 5).astype(float)
    a, b = bootstrap(t1, groups), bootstrap(t5, groups)
    return f"{t1.mean():.3f} [{a[0]:.2f},{a[1]:.2f}] / {t5.mean():.3f} [{b[0]:.2f},{b[1]:.2f}]"


def fixed(D, wd: float, wt: float, wv: float) -> np.ndarray:
    """Ranks under a fixed three-cue fusion (learned CLS, descriptor, stage-1 text) with these weights."""
    return ranks_of(fuse(D["L"]["cls"], D["desc"], D["text"], D["inl"], wd, wt, wv, None), D["exp"])


def shipped(D):
    """Ranks under the shipped fusion: the shipped block's learned cosine, the ROI caption's and the prompt's
    text scores weighed apart."""
    if D["L"]["shipped"] is None:
        exposure = shipped_exposure()
        raise SystemExit(
            f"the dump has no exposure-{exposure:g} features (the shipped learned cue): "
            "run bench/learned_exposure.py on it first"
            if exposure is not None
            else f"the dump has no block-{shipped_block()} features (the shipped learned cue): "
            "run bench/learned_layers.py on it first"
        )
    wd, wt, wp, wv = shipped_weights()
    w = np.array([1 - wd - wt - wp, wd, wt, wp])
    cues = np.stack([D["L"]["shipped"], *FEATSETS[SHIPPED](D)[1:]])
    return ranks_of(scores(cues, w, bonus(D), wv), D["exp"])


def paired_gain(a: np.ndarray, b: np.ndarray, groups: np.ndarray, n: int = 2000, seed: int = 0) -> str:
    """Top-1 of ranks ``a`` minus ranks ``b`` (same queries), with a 95 % bootstrap interval over ``groups``."""
    d = (a <= 1).astype(float) - (b <= 1).astype(float)
    lo, hi = bootstrap(d, groups, n, seed)
    return f"{d.mean():+.3f} [{lo:+.3f}, {hi:+.3f}]"


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--train", action="append", required=True)
    p.add_argument("--test", required=True)
    p.add_argument(
        "--against",
        metavar="DESC,TEXT,VERIFY",
        help="also print each set's paired held-out top-1 gain over a fixed fusion with these weights "
        "(e.g. 0.22,0.51,0.3: the spread weights shipped before), on the synthetic sets and the photos",
    )
    a = p.parse_args()
    trains = [load(Path(d)) for d in a.train]
    test = load(Path(a.test))
    print(
        "test shipped:",
        {
            k: rates(shipped(test)[test["kind"] == k], test["photo"][test["kind"] == k])
            for k in ("mask", "box")
        },
    )
    for D in trains:
        print("train-set shipped", rates(shipped(D), D["label"]))
    pooled = {}
    for name, fn in FEATSETS.items():
        held = cv_ranks(trains, fn)
        cv = [rates(h, D["label"]) for D, h in zip(trains, held, strict=True)]
        w, wv = fit_all(trains, fn)
        r = ranks_of(scores(np.stack(fn(test)), w, bonus(test), wv), test["exp"])
        out = {k: rates(r[test["kind"] == k], test["photo"][test["kind"] == k]) for k in ("mask", "box")}
        print(name, "w", np.round(w, 3), "wv", round(float(wv), 3), "| synth CV", cv, "| photos", out)
        pooled[name] = np.concatenate(held)
        if a.against:
            wd, wt, wv0 = (float(x) for x in a.against.split(","))
            base = [fixed(D, wd, wt, wv0) for D in (*trains, test)]
            gains = [paired_gain(h, b, D["label"]) for h, b, D in zip(held, base[:-1], trains, strict=True)]
            gains += [
                paired_gain(
                    r[test["kind"] == k], base[-1][test["kind"] == k], test["photo"][test["kind"] == k]
                )
                for k in ("mask", "box")
            ]
            print(
                f"  paired top-1 gain over {a.against}: synthetic sets {gains[:-2]}, photos mask / box {gains[-2:]}"
            )
    # the selection rule, declared before looking at the photos: the simplest feature set, unless another
    # one's held-out synthetic top-1 (both sets pooled) is higher with a paired interval above zero
    groups = np.concatenate([D["label"] for D in trains])
    for name, ranks in pooled.items():
        if name != SIMPLEST:
            print(
                f"paired top-1 gain over {SIMPLEST}, synthetic held out: {name} {paired_gain(ranks, pooled[SIMPLEST], groups)}"
            )


if __name__ == "__main__":
    main()

"""A query-side linear adapter for the learned cue, trained on synthetic queries, replayed on feature dumps.

    python bench/learned_adapter.py --store STORE --train SYNTH_DUMP [--train DIR ...] --test PHOTO_DUMP \
        --confirm FRESH_SYNTH_DUMP [--lams 0.01,0.1] [--ranks 8,32]

The dumps are ``bench/learned_features.py``'s with ``bench/learned_exposure.py``'s ``exposure_110.npz`` (the
shipped cue: block 11's CLS on exposure-normalised images). The adapter maps the ROI's vector ``q`` to
``q (I + U W)`` (``U``, ``W`` of rank ``r``; the stored views are not touched, so a store would need no
re-onboarding) and is trained by a softmax over the models' best-view cosines of the right model against the
others (temperature 0.03, Adam, 300 steps, penalty ``lam * |U W|^2`` towards the identity). The photos are
never trained or chosen on. Printed:

1. **Choice of ``lam`` and ``r``**: leave one training dump out (trained on the others, the learned cue alone
   ranked on the one left out); the best mean top-1 is kept.
2. **Library adapter**: trained on every training query (every model of the library has synthetic queries, as
   a library could render for itself at onboarding); the cue alone on the photos and on the fresh dump, whose
   images no training query shares, paired against the cue without the adapter (95 % intervals over objects).
3. **Generic adapter**: trained only on the objects outside the 21 YCB-Video objects, with only their models
   as candidates; the cue alone on the YCB-Video objects (every photo object is one), which it never saw.
4. **Fused**: the shipped cue set (``raw4``) refitted (``bench/learned_ltr.py``'s fit) with the adapted cue,
   each training dump's adapted scores from an adapter trained on the other dumps (so the fusion does not
   learn in-sample scores); photos and fresh dump ranked with the library adapter.

Results: docs/results.md, section 10.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

import learned_ltr as ltr  # noqa: E402
from learned_fusion import l2, ranks_of  # noqa: E402

TARGET = 110  # the shipped exposure target
TEMPERATURE = 0.03
STEPS = 300
SEED = [0]  # the adapters' initial draw (``--seed``)


def loaded(d: Path, mesh_label: dict[str, str]) -> dict:
    """A dump's cues (``bench/learned_ltr.py``'s) plus the shipped cue's ROI and view vectors."""
    D = ltr.load(d)
    a = np.load(d / f"exposure_{TARGET}.npz")
    ids = json.loads((d / "meshes.json").read_text())
    D.update(
        R=l2(a["rois"]), V=l2(a["views"]), vm=a["view_mesh"], mlab=np.array([mesh_label[i] for i in ids])
    )
    return D


def views_by_model(D: dict):
    """The views as a (models, views per model, dim) tensor; every model must have as many views."""
    import torch

    counts = np.bincount(D["vm"])
    if len(set(counts)) != 1:
        raise SystemExit("every model needs the same number of views")
    order = np.argsort(D["vm"], kind="stable")
    return torch.as_tensor(D["V"][order].reshape(len(counts), counts[0], -1))


def model_scores(R: np.ndarray, A, V3):
    """(queries, models): each model's best-view cosine with the adapted, re-normalised ROI vectors."""
    import torch

    q = torch.nn.functional.normalize(torch.as_tensor(R) @ A, dim=1)
    return torch.einsum("qd,nvd->qnv", q, V3).max(-1).values


def train(R: np.ndarray, target: np.ndarray, allowed: np.ndarray, V3, lam: float, rank: int):
    """The adapter matrix ``I + U W`` fitted on ROI vectors ``R`` whose right model is ``target``; only the
    ``allowed`` models compete."""
    import torch

    dim = R.shape[1]
    g = torch.Generator().manual_seed(SEED[0])
    U = torch.zeros(dim, rank, requires_grad=True)
    W = (0.01 * torch.randn(rank, dim, generator=g)).requires_grad_()
    opt = torch.optim.Adam([U, W], lr=3e-3)
    Rt, tt, off = torch.as_tensor(R), torch.as_tensor(target), torch.as_tensor(~allowed)
    for _ in range(STEPS):
        s = model_scores(Rt, torch.eye(dim) + U @ W, V3) / TEMPERATURE
        loss = torch.nn.functional.cross_entropy(s.masked_fill(off[None, :], -1e9), tt)
        loss = loss + lam * (U @ W).pow(2).sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
    return (torch.eye(dim) + U @ W).detach()


def adapted(D: dict, A, V3) -> np.ndarray:
    import torch

    with torch.no_grad():
        return model_scores(D["R"], A, V3).numpy()


def stacked(dumps: list[dict], keep=None) -> tuple[np.ndarray, np.ndarray]:
    """(ROI vectors, right model) of every query of ``dumps`` (those ``keep`` selects)."""
    R, t = [], []
    for D in dumps:
        sel = np.ones(len(D["R"]), bool) if keep is None else keep(D)
        R.append(D["R"][sel])
        t += [e[0] for e, s in zip(D["exp"], sel, strict=True) if s]
    return np.concatenate(R), np.array(t)


def rate(r: np.ndarray) -> str:
    return f"{np.mean(r <= 1):.3f} / {np.mean(r <= 5):.3f}"


def per_kind(D: dict, ranks: np.ndarray, base: np.ndarray, groups: np.ndarray) -> str:
    out = []
    for k in np.unique(D["kind"]):
        s = D["kind"] == k
        out.append(
            f"{k}: {rate(base[s])} -> {rate(ranks[s])}, top-1 {ltr.paired_gain(ranks[s], base[s], groups[s])}"
        )
    return "; ".join(out)


def choose(T: list[dict], grid, V3, names: list[str]) -> tuple[float, int]:
    """The (lam, rank) of ``grid`` with the best mean top-1 on a training dump left out."""
    import torch

    everyone = np.ones(V3.shape[0], bool)
    print("1. choice, leave one training dump out (learned cue alone, top-1 / top-5 on the dump left out):")
    best, best_t1 = grid[0], -1.0
    for lam, r in grid:
        hits, line = [], []
        for i, D in enumerate(T):
            R, t = stacked([E for j, E in enumerate(T) if j != i])
            ranks = ranks_of(adapted(D, train(R, t, everyone, V3, lam, r), V3), D["exp"])
            hits.append(np.mean(ranks <= 1))
            line.append(f"{Path(names[i]).name} {rate(ranks)}")
        print(f"   lam {lam:g} rank {r}: {'; '.join(line)}; mean top-1 {np.mean(hits):.3f}", flush=True)
        if np.mean(hits) > best_t1:
            best, best_t1 = (lam, r), float(np.mean(hits))
    ident = torch.eye(V3.shape[2])
    base = [np.mean(ranks_of(adapted(D, ident, V3), D["exp"]) <= 1) for D in T]
    print(f"   without the adapter: mean top-1 {np.mean(base):.3f}; chosen lam {best[0]:g} rank {best[1]}")
    return best


def main() -> int:
    import torch

    from pipeline.evaluate.library import read_store_meshes
    from pipeline.evaluate.openset import YCB_VIDEO_LABELS

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--store", required=True)
    p.add_argument("--train", action="append", required=True, help="a synthetic dump (repeatable)")
    p.add_argument("--test", required=True, help="the photos' dump (never trained or chosen on)")
    p.add_argument("--confirm", required=True, help="a fresh synthetic dump sharing no image with --train")
    p.add_argument("--lams", default="0.01,0.1")
    p.add_argument("--ranks", default="8,32")
    p.add_argument("--seed", type=int, default=0, help="the adapters' initial draw")
    args = p.parse_args()
    SEED[0] = args.seed
    torch.set_num_threads(2)
    label = {m.mesh_id: m.name[:3] for m in read_store_meshes(args.store)}
    T = [loaded(Path(d), label) for d in args.train]
    P, F = loaded(Path(args.test), label), loaded(Path(args.confirm), label)
    V3 = views_by_model(T[0])
    n = V3.shape[0]
    everyone = np.ones(n, bool)
    ident = torch.eye(V3.shape[2])
    grid = [(float(lam), int(r)) for lam in args.lams.split(",") for r in args.ranks.split(",")]

    if len(T) > 1:
        lam, r = choose(T, grid, V3, args.train)
    elif len(grid) == 1:
        ((lam, r),) = grid
        print(f"1. one training dump: lam {lam:g} rank {r} as given")
    else:
        raise SystemExit("one training dump: give one --lams and one --ranks value (nothing to choose on)")

    print("2. library adapter (every training query), learned cue alone, without -> with:")
    R, t = stacked(T)
    A_lib = train(R, t, everyone, V3, lam, r)
    for name, D, groups in (("photos", P, P["photo"]), (Path(args.confirm).name, F, F["label"])):
        base = ranks_of(adapted(D, ident, V3), D["exp"])
        print(f"   {name}: {per_kind(D, ranks_of(adapted(D, A_lib, V3), D['exp']), base, groups)}")

    print("3. generic adapter (objects outside YCB-Video only), on the YCB-Video objects, without -> with:")
    outside = ~np.isin(T[0]["mlab"], YCB_VIDEO_LABELS)
    R, t = stacked(T, keep=lambda D: ~np.isin(D["label"], YCB_VIDEO_LABELS))
    A_gen = train(R, t, outside, V3, lam, r)
    for name, D, groups in (("photos", P, P["photo"]), (Path(args.confirm).name, F, F["label"])):
        sel = np.isin(D["label"], YCB_VIDEO_LABELS)
        sub = {
            "R": D["R"][sel],
            "kind": D["kind"][sel],
            "exp": [e for e, s in zip(D["exp"], sel, strict=True) if s],
        }
        base = ranks_of(adapted(sub, ident, V3), sub["exp"])
        print(
            f"   {name} (n={int(sel.sum())}): {per_kind(sub, ranks_of(adapted(sub, A_gen, V3), sub['exp']), base, groups[sel])}"
        )

    print("4. fused (raw4 refitted with the adapted cue; training dumps scored out of dump):")
    if len(T) == 1:
        print("   (needs two training dumps or more: each is scored by an adapter trained on the others)")
        return 0
    for i, D in enumerate(T):
        R, t = stacked([E for j, E in enumerate(T) if j != i])
        D["AD"] = adapted(D, train(R, t, everyone, V3, lam, r), V3)
    for D in (P, F):
        D["AD"] = adapted(D, A_lib, V3)
    cues = {
        "shipped": lambda D: [D["L"]["shipped"], *ltr.FEATSETS["raw4"](D)[1:]],
        "adapted": lambda D: [D["AD"], *ltr.FEATSETS["raw4"](D)[1:]],
    }
    weights, full, ranks = {}, {}, {}
    for name, fn in cues.items():
        w, wv = weights[name] = ltr.fit_all(T, fn)
        full[name] = {id(D): ltr.scores(np.stack(fn(D)), w, ltr.bonus(D), wv) for D in (P, F)}
        ranks[name] = {id(D): ranks_of(full[name][id(D)], D["exp"]) for D in (P, F)}
        print(
            f"   {name}: weights learned, descriptor, ROI caption, prompt {np.round(w, 3).tolist()}, verification {wv:.3f}"
        )
    for name, D, groups in (("photos", P, P["photo"]), (Path(args.confirm).name, F, F["label"])):
        print(f"   {name}: {per_kind(D, ranks['adapted'][id(D)], ranks['shipped'][id(D)], groups)}")

    print(
        "5. open set: absent rejected where 95 % of correct top-1 answers are accepted (one feature, threshold"
    )
    print(
        "   set on these answers: compares, does not choose); absent = the YCB-Video objects' queries against"
    )
    print("   the library without them, whose adapter is the one trained on that library (the generic one):")
    for D in (P, F):
        D["AD_absent"] = adapted(D, A_gen, V3)
    for name, D in (("photos", P), (Path(args.confirm).name, F)):
        line = []
        for cue, fn in cues.items():
            w, wv = weights[cue]
            absent_cues = np.stack([D["AD_absent"] if cue == "adapted" else D["L"]["shipped"], *fn(D)[1:]])
            absent_cues[:, :, ~outside] = -10.0  # the left-out models: not in this library
            gone = ltr.scores(absent_cues, w, ltr.bonus(D), wv)[:, outside]
            line.append(f"{cue} {open_set_rates(D, full[cue][id(D)], gone)}")
        print(f"   {name}: {'; '.join(line)}")
    return 0


def top1(s: np.ndarray, feat: str) -> np.ndarray:
    """Each query's best score (``score``) or how many standard deviations it stands above the library (``z``)."""
    t = s.max(axis=1)
    return t if feat == "score" else (t - s.mean(axis=1)) / np.maximum(s.std(axis=1), 1e-6)


def open_set_rates(D: dict, full: np.ndarray, gone: np.ndarray) -> str:
    """Absent rejected at 95 % of correct accepted, by the top-1 score and by its z-score over the library."""
    from pipeline.evaluate.openset import YCB_VIDEO_LABELS

    correct = ranks_of(full, D["exp"]) == 1
    absent = np.isin(D["label"], YCB_VIDEO_LABELS)
    out = []
    for feat in ("score", "z"):
        ok, ab = top1(full, feat)[correct], top1(gone, feat)[absent]
        threshold = np.quantile(ok, 0.05)
        out.append(f"{feat} {100 * np.mean(ab < threshold):.1f} %")
    return f"(correct {int(correct.sum())}, absent {int(absent.sum())}) " + ", ".join(out)


if __name__ == "__main__":
    raise SystemExit(main())

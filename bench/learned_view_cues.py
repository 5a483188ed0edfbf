"""Three more ways to score ROI against views, replayed on feature dumps next to the shipped fusion.

    python bench/learned_view_cues.py --store STORE --train SYNTH_DUMP [--train DIR ...] --test PHOTO_DUMP \
        [--cues chamfer,views24,joint,silhouette]

The dumps are ``bench/learned_features.py``'s (224 px, unflipped, of the same store). Cues:

* ``chamfer``: patch tokens instead of the CLS token. Each ROI foreground patch (off the render gray) takes
  its best cosine with a view's foreground patches, averaged over the ROI's patches (``q2v``), the other
  way round (``v2q``) and their mean (``sym``); max over the model's views. Each is added to the shipped
  cue set (``raw4``) as a fifth cue, and ``sym`` also replaces the CLS cosine; the weights are refitted
  as ``bench/learned_ltr.py`` fits them (synthetic dumps only, 5 folds by object).
* ``views24``: 8 views per elevation ring instead of 4 (24 per model, rendered and embedded here), so
  the learned cosine is a max over twice the viewpoints; ``raw3`` and ``raw4`` refitted on it.
* ``silhouette``: the IoU of the ROI's silhouette (off the render gray, cropped to its box, centred on a
  square, 32 x 32) with each view's, max over the model's views, as a fifth cue (refitted).
* ``joint``: the learned and descriptor cosines of the *same* view (max over views of their weighted sum)
  instead of each one's own best view, mixed with the shipped score by ``lam`` (shipped weights, no refit).

Prints, per cue, the cue alone and fused (top-1 / top-5), held out by object on the synthetic dumps and on
the photos (never fitted on), and the paired held-out top-1 gain over ``raw4`` on the synthetic dumps.
Results: docs/results.md, section 7.2 ("Tried after this choice").
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from PIL import Image

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

import learned_ltr as ltr  # noqa: E402
from learned_features import dump_rois, view_images  # noqa: E402
from learned_fg_pooling import foreground_share  # noqa: E402
from learned_fusion import best_per_model as per_model  # noqa: E402
from learned_fusion import l2, ranks_of  # noqa: E402

SIZE = 224


def fg_patches(images, enc) -> tuple[np.ndarray, np.ndarray]:
    """L2-normalised final-layer patch tokens on the object (over half the 14 px patch off the render gray),
    concatenated, and each image's offsets into them."""
    toks, offs = [], [0]
    for i in range(0, len(images), 32):
        batch = images[i : i + 32]
        for im, t in zip(batch, enc.tokens(batch), strict=True):
            w = foreground_share(im, enc.fill, SIZE)
            sel = w > 0.5
            if sel.sum() < 2:
                sel = w >= np.sort(w)[-2]
            toks.append(l2(t[1:][sel]).astype(np.float16))
            offs.append(offs[-1] + int(sel.sum()))
    return np.concatenate(toks), np.array(offs)


def in_raw4(name: str):
    """The shipped cue set (``raw4``) with the cue ``D[name]`` in place of its learned cosine."""

    def cues(D):
        return [D[name], *ltr.FEATSETS["raw4"](D)[1:]]

    return cues


def replay_parser(doc: str) -> argparse.ArgumentParser:
    """The arguments every dump replay takes: the store, the synthetic dumps fitted on, the photos' dump."""
    p = argparse.ArgumentParser(description=doc.splitlines()[0])
    p.add_argument("--store", required=True)
    p.add_argument("--train", action="append", required=True, help="a synthetic dump (repeatable)")
    p.add_argument("--test", required=True, help="the photos' dump")
    return p


def chamfer(store: str, dumps: list[Path], enc) -> None:
    """Writes ``chamfer_224.npz`` (q2v, v2q, sym: queries x models) into every dump."""
    meshes = json.loads((dumps[0] / "meshes.json").read_text())
    keys, views = view_images(store, meshes)
    t0 = time.perf_counter()
    V, vo = fg_patches(views, enc)
    V = V.astype(np.float32)
    vm = np.array([m for m, _ in keys])
    print(f"view patches: {len(V)} from {len(views)} views in {time.perf_counter() - t0:.1f} s")
    for d in dumps:
        if (d / "chamfer_224.npz").exists():
            continue
        recs = json.loads((d / "queries.json").read_text())
        R, ro = fg_patches(dump_rois(d, recs), enc)
        out = {k: [] for k in ("q2v", "v2q", "sym")}
        for i in range(len(recs)):
            S = R[ro[i] : ro[i + 1]].astype(np.float32) @ V.T
            q2v = np.maximum.reduceat(S, vo[:-1], axis=1).mean(0)
            v2q = np.add.reduceat(S.max(0), vo[:-1]) / np.diff(vo)
            for k, s in (("q2v", q2v), ("v2q", v2q), ("sym", (q2v + v2q) / 2)):
                out[k].append(per_model(s[None], vm, len(meshes))[0])
        np.savez(d / "chamfer_224.npz", **{k: np.stack(v) for k, v in out.items()})


def views24(store: str, out: Path, enc) -> None:
    """Renders every model of the store with 8 views per ring (offline rings) and writes their CLS vectors."""
    from pipeline.mesh.load import load_mesh
    from pipeline.mesh.render import Renderer
    from pipeline.mesh.settings import RenderConfig
    from pipeline.profiles import default_elevations
    from pipeline.store import Store

    if out.exists():
        return
    meshes = json.loads((out.parent / "meshes.json").read_text())
    s = Store.open(store)
    rows = s.read_latest("meshes").to_pylist()
    s.close()
    path = {r["mesh_id"]: (f"{r['library_root']}/{r['source_path']}", r["format"]) for r in rows}
    renderer = Renderer(RenderConfig(elevations_deg=default_elevations("offline"), views_per_ring=8))
    embs, vm = [], []
    t0 = time.perf_counter()
    for j, m in enumerate(meshes):
        views = renderer.render(load_mesh(*path[m], max_faces=10**7))
        embs.append(enc.encode_image([Image.fromarray(v.image) for v in views]))
        vm += [j] * len(views)
    print(f"24 views x {len(meshes)} models rendered and embedded in {time.perf_counter() - t0:.1f} s")
    np.savez(out, views_cls=np.concatenate(embs), view_mesh=np.array(vm))


def silhouette(im: Image.Image, grid: int = 32) -> np.ndarray:
    """The image's pixels off the render gray, cropped to their box, centred on a square, ``grid`` x ``grid``."""
    from pipeline.query.settings import GRAY

    fg = np.abs(np.asarray(im.convert("RGB"), np.float32) - np.array(GRAY, np.float32)).sum(-1) > 8
    ys, xs = np.nonzero(fg)
    if len(ys) < 4:
        return np.zeros(grid * grid, np.float32)
    fg = fg[ys.min() : ys.max() + 1, xs.min() : xs.max() + 1]
    h, w = fg.shape
    side = max(h, w)
    sq = np.zeros((side, side), np.uint8)
    sq[(side - h) // 2 : (side - h) // 2 + h, (side - w) // 2 : (side - w) // 2 + w] = fg * 255
    small = np.asarray(Image.fromarray(sq).resize((grid, grid), Image.Resampling.BILINEAR)) > 127
    return small.reshape(-1).astype(np.float32)


def silhouettes(store: str, dumps: list[Path]) -> None:
    """Writes ``silhouette.npy`` (queries x models: best silhouette IoU over the model's views) into every dump."""
    meshes = json.loads((dumps[0] / "meshes.json").read_text())
    keys, views = view_images(store, meshes)
    VS, vm = np.stack([silhouette(v) for v in views]), np.array([m for m, _ in keys])
    for d in dumps:
        RS = np.stack([silhouette(im) for im in dump_rois(d)])
        inter = RS @ VS.T
        iou = inter / np.maximum(RS.sum(1)[:, None] + VS.sum(1)[None] - inter, 1.0)
        np.save(d / "silhouette.npy", per_model(iou, vm, len(meshes)))


def rates(r: np.ndarray, kind: np.ndarray) -> str:
    return " ".join(
        f"{k} {np.mean(r[kind == k] <= 1):.3f}/{np.mean(r[kind == k] <= 5):.3f}" for k in np.unique(kind)
    )


def joint(store: str, dumps: list[Path]) -> None:
    """Shipped weights; the learned + descriptor part taken per view (``lam`` 1) or per cue (``lam`` 0)."""
    from pipeline.models import create_model
    from pipeline.profiles import PROFILES
    from pipeline.store import Store

    enc = create_model("view_encoder", PROFILES["offline"].view_encoder)
    meshes = json.loads((dumps[0] / "meshes.json").read_text())
    at = {m: i for i, m in enumerate(meshes)}
    s = Store.open(store)
    table = next(t for t in s.all_datasets() if t.startswith("image_embeddings/descriptor"))
    rows = sorted(
        (at[r["mesh_id"]], r["view_index"], r["embedding"]) for r in s.read_latest(table).to_pylist()
    )
    s.close()
    DV, dvm = l2(np.array([r[2] for r in rows], np.float32)), np.array([r[0] for r in rows])
    wd, wt, wp, wv = ltr.shipped_weights()
    wl = 1 - wd - wt - wp
    for d in dumps:
        D = ltr.load(d)
        a = np.load(d / "feat_224_0.npz")
        rois = dump_rois(d, D["recs"])
        sd = l2(np.asarray(enc.encode_image(rois), np.float32)) @ DV.T
        sl = l2(a["rois_cls"]) @ l2(a["views_cls"]).T
        both = per_model(wl * sl + wd * sd, dvm, len(meshes))
        apart = wl * D["L"]["cls"] + wd * D["desc"]
        for lam in (0.0, 0.5, 1.0):
            base = lam * both + (1 - lam) * apart + wt * D["troi"] + wp * D["tpr"]
            r = ranks_of(ltr.scores(base[None], np.ones(1), ltr.bonus(D), wv), D["exp"])
            print(f"joint {d.name} lam {lam}: {rates(r, D['kind'])}")


def refit(trains: list[str], test: str, featsets: dict, patch, simplest: str = "raw4") -> None:
    """``bench/learned_ltr.py``'s fit and report, with ``patch`` adding cues to every loaded dump; the
    paired gains are printed against ``simplest``."""
    plain = ltr.load

    def load(d):
        return patch(plain(d), Path(d))

    saved = ltr.load, ltr.FEATSETS, ltr.SIMPLEST, sys.argv
    ltr.load, ltr.FEATSETS, ltr.SIMPLEST = load, featsets, simplest
    sys.argv = [sys.argv[0], *sum((["--train", t] for t in trains), []), "--test", test]
    try:
        ltr.main()
    finally:
        ltr.load, ltr.FEATSETS, ltr.SIMPLEST, sys.argv = saved


def main() -> int:
    p = replay_parser(__doc__)
    p.add_argument("--cues", default="chamfer,views24,joint,silhouette")
    args = p.parse_args()
    from pipeline.models.focus_encoder import LearnedViewEncoder

    cues = set(args.cues.split(","))
    dumps = [Path(d) for d in (*args.train, args.test)]
    enc = LearnedViewEncoder(size=SIZE)
    raw4 = ltr.FEATSETS["raw4"]

    def alone(D, d, name, s):
        print(f"{name} alone, {d.name}: {rates(ranks_of(s, D['exp']), D['kind'])}")

    if "chamfer" in cues:
        chamfer(args.store, dumps, enc)

        def add_chamfer(D, d):
            c = np.load(d / "chamfer_224.npz")
            D |= {k: c[k] for k in ("q2v", "v2q", "sym")}
            for k in ("q2v", "v2q", "sym"):
                alone(D, d, k, D[k])
            return D

        refit(
            args.train,
            args.test,
            {
                "raw4": raw4,
                "raw4+q2v": lambda D: [*raw4(D), D["q2v"]],
                "raw4+v2q": lambda D: [*raw4(D), D["v2q"]],
                "raw4+sym": lambda D: [*raw4(D), D["sym"]],
                "sym-for-cls": in_raw4("sym"),
            },
            add_chamfer,
        )
    if "views24" in cues:
        path = dumps[-1] / "views24_224.npz"
        views24(args.store, path, enc)
        v = np.load(path)
        vc, vm = l2(v["views_cls"]), v["view_mesh"]

        def use_24(D, d):
            rois = l2(np.load(d / "feat_224_0.npz")["rois_cls"])
            alone(D, d, "CLS, 12 views", D["L"]["cls"])
            D["L"]["cls"] = per_model(rois @ vc.T, vm, D["L"]["cls"].shape[1])
            alone(D, d, "CLS, 24 views", D["L"]["cls"])
            return D

        refit(args.train, args.test, {"raw3": ltr.FEATSETS["raw3"], "raw4": raw4}, use_24)
    if "silhouette" in cues:
        silhouettes(args.store, dumps)

        def add_silhouette(D, d):
            D["silhouette"] = np.load(d / "silhouette.npy")
            alone(D, d, "silhouette IoU", D["silhouette"])
            return D

        refit(
            args.train,
            args.test,
            {"raw4": raw4, "raw4+silhouette": lambda D: [*raw4(D), D["silhouette"]]},
            add_silhouette,
        )
    if "joint" in cues:
        joint(args.store, dumps)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
